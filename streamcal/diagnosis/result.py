"""The result of a diagnosis (:func:`streamcal.diagnosis.diagnose`): a value — frozen all the
way down, equal when its JSON content is, round-tripping through :meth:`Diagnosis.to_dict` and
:meth:`Diagnosis.from_dict`, shown as HTML in Jupyter. One type for every starting point: a
diagnosis against a held calibration carries its :class:`~streamcal.diagnosis.held.part.HeldPart`
in ``held``."""
from __future__ import annotations

import dataclasses
import html
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ..calibration import jsonable
from ..units import quantity
from ..values import FrozenDict, freeze, html_table, same, thaw
from . import candidates as cand
from . import verdict as verdict_mod
from .held.part import HeldPart
from .text import TOP, diagnosis_unit, short_repr, summary as summary_lines


#: The keys of a diagnosis' JSON that say which samples its figures used (``sampling``).
SAMPLING_KEYS = ("samples_used", "samples_total", "subsample_rule", "outlier_spans_over",
                 "n_outliers_recording")
#: ``sampling`` when every sample was used.
EVERY_SAMPLE = "every sample"
#: The fields holding containers: stored deep-frozen (:func:`streamcal.values.freeze`).
_CONTAINERS = ("candidates", "outlier_spans", "ladder", "residual_families", "noise", "misfit",
               "sampling", "next_step", "heading_error_deg", "location", "tied_noise_floors",
               "heading_check")


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """Result of :func:`diagnose`; ``to_dict`` gives the JSON of docs/cli.md plus ``ladder``,
    ``noise``, ``residual_families``, ``residual``, ``candidate_baselines``,
    ``outliers_model`` and ``n_outliers_model``. rms, noise_floor and rms_after in the sensor
    unit (``unit``).

    A value: frozen (:meth:`replace` derives a changed one), its containers read-only (tuples,
    :class:`~streamcal.values.FrozenDict`: ladder steps read like dicts), equal to another when
    their JSON contents are (:meth:`to_dict` after :func:`streamcal.calibration.jsonable`:
    arrays as lists, a NaN "no value" as null, so NaN equals NaN), and
    ``Diagnosis.from_dict(d.to_dict()) == d``. What the JSON does not carry takes no part in
    equality and is absent (None) after :meth:`from_dict`: the per-sample ``outliers`` mask
    (its count and spans are carried), the fitted ``calibration`` and the candidates' refits,
    ``subsample`` (the Track a long recording was diagnosed from), its ``gravity`` reference
    and ``location`` (the place of the heading error).

    ``held``: None for a fresh fit; for a diagnosis against a given (or the stated default)
    calibration, the :class:`~streamcal.diagnosis.held.part.HeldPart` saying what was held and
    what re-estimated (its keys are top-level keys of the JSON; ``held`` marks it).

    Which residual each rms is on (``residual``: ``"sensor"``, eq. 41 with free directions;
    ``"gravity_tied"`` or ``"gyro_tied"``, see :mod:`streamcal.diagnosis.candidates`): ``rms`` is
    on ``residual`` (the base model's); each candidate's ``rms_after`` is on the residual named
    in ``candidate_baselines[effect]``, beside ``rms_before``, the model without the effect on
    that same residual — compare a candidate with its ``rms_before``, never with another
    residual's rms. Each ladder step carries its ``residual`` and (after the first) the
    ``rms_before`` it was compared with. ``noise_floor`` is on the sensor residual; the floor of
    each tied residual the diagnosis used is in ``tied_noise_floors``
    (:mod:`streamcal.diagnosis.tied_noise`), and :meth:`floor_for` gives the one a residual is
    judged against.

    Outliers: ``n_outliers`` belongs with ``model`` and ``rms`` (docs/cli.md): the base model's
    outliers, the complement of the samples its rms is over. ``outlier_spans``, the (N,) bool
    mask ``outliers`` and its count ``n_outliers_model`` come from one model,
    ``outliers_model``: the last magnetometer-only (sensor residual) model of the ladder — the
    base model when the ladder added nothing. A missing effect makes the base model's residual
    large wherever the effect is (e.g. far from T0): those are not outliers, so the spans are
    drawn from the model that has the effect.
    """

    model: tuple[str, ...]
    n: int
    n_outliers: int
    rms: float
    noise_floor: float
    verdict: str
    candidates: tuple
    outlier_spans: tuple
    ladder: tuple = ()
    residual_families: Mapping = field(default_factory=FrozenDict)
    noise: Mapping = field(default_factory=FrozenDict)
    calibration: object = field(default=None, repr=False)
    residual: str = "sensor"
    outliers_model: tuple[str, ...] = ()
    outliers: np.ndarray | None = field(default=None, repr=False)
    n_outliers_model: int | None = None
    #: False when the recording cannot measure the floor (``noise_floor`` is then NaN, null in
    #: the JSON); ``noise_floor_reason`` says why.
    noise_floor_reliable: bool = True
    noise_floor_reason: str = ""
    noise_floor_rule: str = field(default_factory=verdict_mod.floor_rule)
    #: ``{residual: {"floor", "reliable", "reason", "magnetometer_part", "reference_part",
    #: "method"}}`` for each gravity- or gyro-tied residual the diagnosis judged (sensor unit;
    #: floor null when not measurable).
    tied_noise_floors: Mapping = field(default_factory=FrozenDict)
    significance_rule: str = field(default_factory=verdict_mod.significance_rule)
    #: Where the base model's residual energy sits (:func:`streamcal.diagnosis.misfit.localise`).
    misfit: Mapping | None = None
    #: Which samples the figures used (:mod:`streamcal.diagnosis.subsample`); None: every one.
    sampling: Mapping | None = None
    #: Plain sentences (:func:`streamcal.diagnosis.advice.summary`), the command they advise
    #: (argv, None: nothing to do) and the heading error the ladder's first and last rms imply
    #: (None: the horizontal field is unknown, ``heading_error_reason`` says why).
    summary: str = ""
    next_step: tuple[str, ...] | None = None
    heading_error_deg: Mapping | None = None
    heading_error_reason: str = ""
    #: The sensor unit of every rms ("" when not known).
    unit: str = ""
    #: What a diagnosis against a held calibration adds (None: a fresh fit).
    held: HeldPart | None = None
    #: The subsample Track a long recording was diagnosed from (None: the recording itself).
    subsample: object = field(default=None, repr=False, compare=False)
    #: The World Magnetic Model field (:func:`streamcal.geomag.wmm_field`) at the place and date
    #: the heading error used: the one given, else the log's GPS position (None: neither).
    location: Mapping | None = field(default=None, repr=False, compare=False)
    #: The gravity reference the diagnosis was judged with (a subsample's built on the chunks
    #: read, :meth:`streamcal.diagnosis.subsample.StratifiedSampler.gravity`), for what is said
    #: beside it to reuse; None when it needed none.
    gravity: object = field(default=None, repr=False, compare=False)
    #: Heading error (degrees) against the logged attitude of the calibration held and of the
    #: refinement ``next_step`` writes (:func:`streamcal.fitting.heading_check.heading_check`);
    #: None without an attitude, a held calibration or a refinement.
    heading_check: Mapping | None = None
    #: The calibration of the ladder's last model, fitted on every sample (what ``next_step``
    #: writes); None when the ladder adds nothing or the engine does not keep it.
    last_calibration: object = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "model", tuple(self.model))
        object.__setattr__(self, "outliers_model", tuple(self.outliers_model or ()))
        for name in _CONTAINERS:
            object.__setattr__(self, name, freeze(getattr(self, name)))
        if self.outliers is not None:
            mask = np.array(self.outliers, dtype=bool)
            mask.flags.writeable = False
            object.__setattr__(self, "outliers", mask)

    def __eq__(self, other) -> bool:
        if not isinstance(other, Diagnosis):
            return NotImplemented
        return type(self) is type(other) and same(jsonable(self._json_fields()),
                                                   jsonable(other._json_fields()))

    __hash__ = None   # holds floats compared NaN-safe

    def replace(self, **changes) -> "Diagnosis":
        """A copy with some fields changed (:func:`dataclasses.replace`)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_dict(cls, d: dict) -> "Diagnosis":
        """The diagnosis a :meth:`to_dict` (or the JSON of ``streamcal diagnose --json``)
        describes, with its ``held`` part when the JSON has the key ``held``.
        Null numbers come back as NaN; ``outliers``, ``calibration`` and the candidates' refits
        are None (the JSON does not carry them). ``d`` is copied (frozen), not shared."""
        values = {}
        for f in dataclasses.fields(cls):
            if f.name not in d or not f.init or f.name == "held":
                continue
            v = d[f.name]
            if f.name in ("model", "outliers_model"):
                v = tuple(v)
            elif f.name == "candidates":
                v = tuple(cand.Candidate.from_dict(c) for c in v)
            elif f.name in ("rms", "noise_floor"):
                v = float("nan") if v is None else float(v)
            values[f.name] = v
        values["held"] = HeldPart.from_dict(d)
        sampling = {k: d[k] for k in SAMPLING_KEYS if k in d}
        values["sampling"] = None if sampling.get("subsample_rule", EVERY_SAMPLE) == \
            EVERY_SAMPLE else sampling
        return cls(**values)

    def _repr_html_(self) -> str:
        """Jupyter's view: verdict, summary sentences, rms and floor with units, the ladder
        (each step with its n) and the top candidates; every text escaped."""
        u = diagnosis_unit(self)
        head = html_table(self._html_rows(u), caption=type(self).__name__)
        steps = html_table(
            [(f"+ {s['added']}" if s.get("added") else ", ".join(s["model"]), s["residual"],
              quantity(s["rms_before"], u, 4) if "rms_before" in s else "–",
              quantity(s["rms"], u, 4), s["n"], s["n_outliers"]) for s in self.ladder],
            header=("step", "residual", "rms before", "rms", "n", "outliers"), caption="ladder")
        cands = html_table(
            [(c.effect, c.residual, quantity(self.baseline(c)[1], u, 4),
              quantity(c.rms_after, u, 4), c.n, f"{c.p_value:.2g}", c.evidence)
             for c in self.candidates[:TOP]],
            header=("effect", "residual", "rms before", "rms after", "n", "p", "evidence"),
            caption=f"candidates (top {min(TOP, len(self.candidates))} of "
                    f"{len(self.candidates)})")
        sentences = f"<p>{html.escape(self.summary)}</p>" if self.summary else ""
        return f"<div>{head}{sentences}{steps}{cands}</div>"

    def _html_rows(self, u: str) -> list[tuple[str, str]]:
        """The label and value rows at the head of :meth:`_repr_html_` (``u``: sensor unit)."""
        floor = quantity(self.noise_floor, u, 4) if self.floor_known else "not measurable"
        rows = [("verdict", self.verdict), ("model", ", ".join(self.model)),
                ("rms", f"{quantity(self.rms, u, 4)} ({self.residual} residual)"),
                ("noise floor", floor), ("samples", f"{self.n} ({self.n_outliers} outliers)"),
                *([("against", self.held.calibration_source),
                   ("held", ", ".join(self.held.parameters) or "none")] if self.held else [])]
        if self.residual != "sensor":   # the floor its rms is judged against
            own = self.floor_for(self.residual)
            rows.insert(3, (f"{self.residual.replace('_', '-')} floor",
                            quantity(own, u, 4) if np.isfinite(own) else "not measurable"))
        return rows

    def __str__(self) -> str:
        return summary_lines(self)

    def __repr__(self) -> str:
        return short_repr(self)

    @property
    def floor_known(self) -> bool:
        """A noise floor this recording measured (ratios to it may be shown)."""
        return bool(self.noise_floor_reliable and np.isfinite(self.noise_floor))

    def floor_for(self, residual: str) -> float:
        """The noise floor (sensor unit) a rms on ``residual`` is judged against: the
        magnetometer's for the sensor residual, the tied residual's own for a tied one; NaN
        when not measured."""
        if residual == "sensor":
            return float(self.noise_floor) if self.floor_known else float("nan")
        entry = (self.tied_noise_floors or {}).get(residual) or {}
        value = entry.get("floor")
        return float(value) if entry.get("reliable") and value is not None else float("nan")

    def baseline(self, candidate) -> tuple[str, float]:
        """``(residual, rms_before)`` of a candidate: the residual family its ``rms_after`` is
        on and the rms of the model without it on that residual (sensor unit)."""
        before = candidate.rms_before
        return candidate.residual, float(self.rms if before is None else before)

    def candidate_baselines(self) -> dict:
        """``{effect: {"residual": …, "rms_before": …}}`` for every candidate."""
        out = {}
        for c in self.candidates:
            residual, before = self.baseline(c)
            out[c.effect] = {"residual": residual, "rms_before": before}
        return out

    def candidate_dict(self, c) -> dict:
        """A candidate's JSON: its residual, ``rms_before`` on it, and the two tests apart; an
        implausible candidate (:func:`streamcal.diagnosis.held.plausibility.implausible_effect`)
        is neither significant nor material, and ``implausible`` says why."""
        residual, before = self.baseline(c)
        significant, material = cand.tests(before, c.rms_after, c.p_value,
                                           self.floor_for(residual))
        out = {**c.to_dict(), "residual": residual, "rms_before": before,
               "significant": significant, "material": material}
        if c.implausible:
            out.update(significant=False, material=False, implausible=c.implausible)
        return out

    def to_dict(self) -> dict:
        """The JSON content in plain lists and dicts of its own (changing them leaves the value
        as it is)."""
        return thaw(self._json_fields())

    def _json_fields(self) -> dict:
        return {"model": list(self.model), "n": self.n, "n_outliers": self.n_outliers,
                "rms": self.rms,
                "noise_floor": float(self.noise_floor) if self.floor_known else None,
                "noise_floor_reliable": self.floor_known,
                "noise_floor_reason": self.noise_floor_reason,
                "noise_floor_rule": self.noise_floor_rule, "verdict": self.verdict,
                "tied_noise_floors": self.tied_noise_floors,
                "significance_rule": self.significance_rule, "misfit": self.misfit,
                "candidates": [self.candidate_dict(c) for c in self.candidates],
                "outlier_spans": self.outlier_spans, "residual": self.residual,
                "candidate_baselines": self.candidate_baselines(),
                "outliers_model": list(self.outliers_model or self.model),
                "n_outliers_model": (self.n_outliers if self.n_outliers_model is None
                                     else self.n_outliers_model),
                "summary": self.summary, "next_step": self.next_step,
                "heading_error_deg": self.heading_error_deg,
                "heading_error_reason": self.heading_error_reason,
                "heading_check": self.heading_check,
                "ladder": self.ladder, "noise": self.noise,
                "residual_families": self.residual_families, "unit": self.unit,
                **(self.sampling or {"samples_used": self.n, "samples_total": self.n,
                                     "subsample_rule": EVERY_SAMPLE}),
                **(self.held.json_fields(self.n) if self.held is not None else {})}
