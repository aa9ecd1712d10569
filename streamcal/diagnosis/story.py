"""One story: every before/after pair a diagnosis shows, on one sample set, with its n.

Both starting points (a fresh fit, a calibration held where the slice cannot determine it) hand
their fitted models here as *evaluations*: objects with ``rss`` (N,) squared residual norms,
``r`` (N,3) residuals, ``inliers`` (N,) bool (the one outlier rule of
:mod:`streamcal.fitting.outlier_rule`, applied per model) and ``p`` (free parameters).

- A candidate is compared with the model it extends on the samples that are not outliers of the
  model *with* the candidate: what the effect explains is counted, true outliers are not.
- The ladder is computed on the samples that are not outliers of its last model (of its last
  model on each residual, when it moves to a tied one): every step has the same ``n`` and its
  ``rms_before`` is the rms of the step above on the same residual; the candidates the ladder
  adds carry its numbers.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import candidates as cand


@dataclass(frozen=True)
class Comparison:
    """A model without (``before``) and with (``after``) one effect, rms on one residual over
    the same ``n`` samples, and the F test's ``p_value`` on them."""

    before: float
    after: float
    n: int
    p_value: float


def rms_over(ev, mask: np.ndarray) -> float:
    """rms (sensor unit) of an evaluation's residual over the (N,) bool ``mask``."""
    mask = np.asarray(mask, bool)
    return float(np.sqrt(np.mean(ev.rss[mask]))) if mask.any() else float("nan")


def compare(ref, ev, mask: np.ndarray | None = None) -> Comparison:
    """``ref`` (the model without the effect) against ``ev`` (with it) on ``mask`` (default: the
    samples that are not outliers of ``ev``), the samples in the F test counted by their
    effective number (lag-1 autocorrelation of ``ev``'s residuals)."""
    mask = np.asarray(ev.inliers if mask is None else mask, bool)
    if len(ref.rss) != len(mask):
        raise ValueError(f"the two models were evaluated on different samples "
                         f"({len(ref.rss)} and {len(mask)})")
    p_value = cand.f_test(float(ref.rss[mask].sum()), float(ev.rss[mask].sum()),
                          max(ev.p - ref.p, 1), cand.effective_n(ev.r[mask]), ev.p)
    return Comparison(rms_over(ref, mask), rms_over(ev, mask), int(mask.sum()), p_value)


def ladder_samples(base, residual_of, added) -> np.ndarray:
    """(N,) bool: the samples every step of the ladder is over — those that are not outliers of
    its last model. A ladder that moves to a gravity- or gyro-tied residual has a last model on
    each residual, whose outliers are judged on different residuals: a sample kept is then an
    inlier of the last model on every residual of the ladder."""
    last = {residual_of(base): base}
    for c in added:
        last[residual_of(c._evaluated)] = c._evaluated
    keep = np.ones(len(base.rss), bool)
    for ev in last.values():
        keep &= np.asarray(ev.inliers, bool)
    return keep


def ladder(model, base, residual_of, added) -> tuple[list[dict], list]:
    """``(steps, added)``: the ladder's steps (SPEC §4 "One story") and the added candidates
    carrying the same numbers (new values; the candidates given are not changed).

    ``base``: the diagnosed model's evaluation; ``residual_of(ev)`` names an evaluation's
    residual; ``added``: the candidates in the order added, each with ``_evaluated`` (the model
    with it) and ``_reference`` (the model without it on the same residual: the step above, or
    its tied refit when the step is the first on a tied residual)."""
    keep = ladder_samples(base, residual_of, added)
    n = int(keep.sum())
    steps = [{"model": list(model), "residual": residual_of(base), "rms": rms_over(base, keep),
              "n": n, "n_outliers": int((~np.asarray(base.inliers, bool)).sum())}]
    names, carried = list(model), []
    for c in added:
        ev, ref = c._evaluated, c._reference
        names.append(c.effect)
        step = compare(ref, ev, keep)
        carried.append(c.replace(rms_before=step.before, rms_after=step.after, n=step.n,
                                 p_value=step.p_value))
        steps.append({"model": list(names), "added": c.effect, "residual": residual_of(ev),
                      "rms": step.after, "rms_before": step.before, "n": n,
                      "n_outliers": int((~np.asarray(ev.inliers, bool)).sum()),
                      "p_value": step.p_value})
    return steps, carried


def climb(ranked: list, rank_after: Callable, *, max_steps: int,
          on_every_sample: Callable | None = None, barred: dict | None = None) -> list:
    """The candidates the ladder adds, in order — the one loop of every starting point: while
    the best of a ranking is significant (and, when ``on_every_sample(candidate, added so far)``
    refits it on every sample, still is), add it and rank the rest on top of the model reached
    with ``rank_after(added so far, effect names)``, at most ``max_steps`` times. Effects that explained
    nothing significant alone (p ≥ :data:`~streamcal.diagnosis.candidates.P_VALUE`) are not
    retried. ``barred``: {step index: effect names not taken at that step} (they may be
    taken at a later one)."""
    barred = barred or {}
    added, current = [], ranked
    while current and len(added) < max_steps:
        skip = barred.get(len(added), ())
        top = next((c for c in current if c.significant and c.effect not in skip), None)
        if top is None:
            break
        if on_every_sample is not None:
            top = on_every_sample(top, added)
            if not top.significant:
                break
        added.append(top)
        rest = [c.effect for c in current if c.effect != top.effect and c.p_value < cand.P_VALUE]
        current = rank_after(added, rest) if rest else []
    return added


#: How many times :func:`climb_supported` climbs again with an unsupported step barred.
RECLIMBS = 6


def climb_supported(ranked: list, rank_after: Callable, *, max_steps: int, model, base,
                    residual_of: Callable, judge: Callable,
                    on_every_sample: Callable | None = None) -> list:
    """:func:`climb`, then, while a step of the ladder its climb gives is not supported by the
    ladder's own numbers (``judge`` on the candidates of :func:`ladder`, as :func:`tell`
    judges them), climb again with that effect barred from that step (at most
    :data:`RECLIMBS` times). Why: each step is ranked on the samples of the model it
    extends, the ladder is told on those of its last model; an effect ranked first on fewer
    samples (a temperature drift, before the motor field that the last model's samples hold)
    can fail there while the same effects added in another order are each supported."""
    barred: dict[int, set] = {}
    added = climb(ranked, rank_after, max_steps=max_steps, on_every_sample=on_every_sample)
    for _ in range(RECLIMBS):
        _, shown = ladder(model, base, residual_of, added)
        failed = next((k for k, c in enumerate(shown) if not judge(c)), None)
        if failed is None:
            break
        barred.setdefault(failed, set()).add(added[failed].effect)
        added = climb(ranked, rank_after, max_steps=max_steps, on_every_sample=on_every_sample,
                      barred=barred)
    return added


def tell(model, base, residual_of: Callable, added: list, ranked: list,
         judge: Callable) -> tuple[list[dict], list, list]:
    """``(steps, added, ranked)``: the :func:`ladder` of the ``added`` candidates, those
    candidates with the ladder's numbers judged by ``judge(candidate) -> significant`` (the
    same rule on the numbers shown; the ladder stops before the first step its own numbers do
    not support), and the ranking with them in place of their first-round selves."""
    while True:
        steps, shown = ladder(model, base, residual_of, added)
        shown = [c.replace(significant=judge(c)) for c in shown]
        failed = [k for k, c in enumerate(shown) if not c.significant]
        if not failed:
            break
        # a step that its own numbers do not support ends the ladder there (its samples
        # change with its last model, so the rest is computed again)
        added = added[:failed[0]]
    by_effect = {c.effect: c for c in shown}
    return steps, shown, [by_effect.get(c.effect, c) for c in ranked]


def change_percent(before: float, after: float, digits: int = 4) -> float | None:
    """``100 (after / before − 1)`` of the two numbers as shown with ``digits`` significant
    digits — the percentage printed beside them; None when it cannot be said."""
    if not (np.isfinite(before) and np.isfinite(after)):
        return None
    before, after = float(f"{before:.{digits}g}"), float(f"{after:.{digits}g}")
    return 100.0 * (after / before - 1.0) if before > 0 else None
