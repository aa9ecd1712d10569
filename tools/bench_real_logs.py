"""The core fit on real recorded logs (``data/real/tracks`` under ``STREAMCAL_SHARED``, see its
SOURCES.md).

    python tools/bench_real_logs.py [--part a|b|c] [--seed 0]

(a) Injected outliers. On six clean logs, gross outliers drawn uniformly in the data's bounding
    box expanded ×1.5 about its centre (seeded) are *appended* so that they make 10 % / 30 % of
    the samples; reported: how far (eq. 40, %) each method's fit moves from its own fit on the
    untouched log. Target: autocal ≤ 1 %.
(b) Real outliers. ``jr_altimu10v3_accmag_s1`` (4 gross outliers at the start) fitted whole and
    without its first 4 rows, each vs the same method's fit on the clean session s2. BROAD trial
    32 (magnet attached 38–95 s) fitted whole vs the fit of its undisturbed part (t < 34 s or
    t > 100 s) — target ≤ 2 % — and both vs trial 02 (the same IMU, undisturbed).
(c) The eight ``tiva_mpu9250_mag_*`` sessions (one MPU-9250, one day): Table IV / V analogues
    for every method: eq. 40 deviation from the method's own fit on the reference session 03 (the
    cleanest, SOURCES.md), and eq. 41 average sensor estimation error on session 03 of the model
    learnt on each session (``streamcal.fitting.estimation_error``). Reported, not judged.

Fits are called with the default coverage check; where a log is refused the fit is repeated
with ``check_coverage=False`` and the cell is marked ``*``. ``fail`` = the method produced no
ellipsoid (exception).
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from _bench_common import normalized_error, real_track, run_stamp

from streamcal.errors import InsufficientDataError
from streamcal.fitting import METHODS, estimation_error, fit

CLEAN = ("sunsided_set2_fullsphere", "freeimucal_mag_data", "jr_altimu10v3_accmag_s2",
         "jr_bno055_accmag", "broad_02_undisturbed_slow_rotation_B", "tiva_mpu9250_mag_03")
TIVA = ("01", "02", "03", "05", "06", "07", "08", "09")
TIVA_REF = "03"
BASIC = {"autocal": {}, "l2_ellipsoid": {"method": "l2_ellipsoid"}, "magical": {"method": "magical"}}


def all_variants():
    cols = {"autocal": {}}
    cols.update({f"autocal/{k}": {"kernel": k} for k in ("cauchy", "huber", "gm", "l1", "l2")})
    cols.update({mt: {"method": mt} for mt in METHODS if mt != "autocal"})
    return cols


FAILURES: list[str] = []


class Fitted:
    """A fit result or its failure, with whether the coverage check had to be switched off."""

    def __init__(self, m, label: str = "", **kw):
        self.forced = False
        self.cal = None
        self.error = ""
        try:
            try:
                self.cal = fit(m, **kw)
            except InsufficientDataError:
                self.forced = True
                self.cal = fit(m, check_coverage=False, **kw)
        except Exception as exc:  # noqa: BLE001 — a method breaking down is a result
            self.error = f"{type(exc).__name__}: {exc}"
            FAILURES.append(f"{label} {kw or ''} on {len(m)} samples"
                            f"{' (coverage check off)' if self.forced else ''}: {self.error}")

    def dev(self, ref: "Fitted") -> float:
        if self.cal is None or ref.cal is None:
            return np.nan
        return normalized_error(self.cal.K, self.cal.b, ref.cal.K, ref.cal.b)

    def mark(self, ref: "Fitted | None" = None) -> str:
        return "*" if self.forced or (ref is not None and ref.forced) else ""


def scale_free(f: Fitted, ref: Fitted) -> tuple[float, float]:
    """(shape deviation of K/det(K)^⅓, ‖b − b_ref‖ / det(K_ref)^⅓): eq. 40 with the field
    strength divided out (indoor sessions see different field magnitudes)."""
    if f.cal is None or ref.cal is None:
        return np.nan, np.nan
    r, r0 = np.cbrt(np.linalg.det(f.cal.K)), np.cbrt(np.linalg.det(ref.cal.K))
    shape = float(np.linalg.norm(f.cal.K / r - ref.cal.K / r0) / np.linalg.norm(ref.cal.K / r0))
    return shape, float(np.linalg.norm(f.cal.b - ref.cal.b) / r0)


def cell(value: float, mark: str = "", digits: int = 2) -> str:
    return ("fail" if not np.isfinite(value) else f"{100 * value:.{digits}f}%") + mark


def with_outliers(m: np.ndarray, fraction: float, rng) -> np.ndarray:
    """Append uniform outliers in the bounding box ×1.5 so that they are ``fraction`` of all."""
    lo, hi = m.min(axis=0), m.max(axis=0)
    c, h = (lo + hi) / 2, 1.5 * (hi - lo) / 2
    k = int(round(fraction * len(m) / (1 - fraction)))
    return np.vstack([m, rng.uniform(c - h, c + h, (k, 3))])


def part_a(seed: int) -> None:
    print("\n### (a) Appended gross outliers: deviation (eq. 40) from the same method's fit on the "
          "untouched log\n")
    print("| log | N | autocal 10 % | autocal 30 % | L2 ellipsoid 10 % | L2 30 % | MAGICAL 10 % | "
          "MAGICAL 30 % | autocal outliers found (10 % / 30 %) |")
    print("|---|---|---|---|---|---|---|---|---|")
    worst = 0.0
    for name in CLEAN:
        m = real_track(name).mag
        rng = np.random.default_rng(seed)
        dirty = {f: with_outliers(m, f, rng) for f in (0.10, 0.30)}
        cells, found = [], []
        for label, kw in BASIC.items():
            ref = Fitted(m, name, **kw)
            for f in (0.10, 0.30):
                r = Fitted(dirty[f], f"{name}+{f:.0%}", **kw)
                d = r.dev(ref)
                cells.append(cell(d, r.mark(ref)))
                if label == "autocal":
                    worst = max(worst, d if np.isfinite(d) else np.inf)
                    if r.cal is not None:
                        extra = r.cal.inliers[len(m):]
                        found.append(f"{(~extra).mean():.1%}")
        print(f"| {name} | {len(m)} | " + " | ".join(cells) + f" | {' / '.join(found)} |")
    print(f"\nTarget autocal ≤ 1 % on every log: worst {100 * worst:.2f}% → "
          f"{'PASS' if worst <= 0.01 else 'FAIL'}")


def part_b() -> None:
    print("\n### (b) Real outliers\n")
    s1 = real_track("jr_altimu10v3_accmag_s1").mag
    s2 = real_track("jr_altimu10v3_accmag_s2").mag
    cols = {"autocal": {}, "l1_ellipsoid": {"method": "l1_ellipsoid"}, **{k: v for k, v in BASIC.items() if k != "autocal"}}
    print("AltIMU-10 v3, deviation (eq. 40) from the same method's fit on the clean session s2:\n")
    print("| method | s1 whole (291 rows) | s1 without rows 0–3 | outliers flagged in s1 rows 0–3 |")
    print("|---|---|---|---|")
    for label, kw in cols.items():
        ref = Fitted(s2, "s2", **kw)
        whole = Fitted(s1, "s1", **kw)
        trimmed = Fitted(s1[4:], "s1[4:]", **kw)
        flagged = (f"{int((~whole.cal.inliers[:4]).sum())} of 4 ({whole.cal.n_outliers} in all)"
                   if whole.cal is not None and label == "autocal" else "")
        print(f"| {label} | {cell(whole.dev(ref), whole.mark(ref))} | "
              f"{cell(trimmed.dev(ref), trimmed.mark(ref))} | {flagged} |")

    b32 = real_track("broad_32_attached_magnet_1cm")
    b02 = real_track("broad_02_undisturbed_slow_rotation_B").mag
    m32, t32 = b32.mag, b32.t_mag
    calm = (t32 < 34.0) | (t32 > 100.0)
    print(f"\nBROAD 32 ({len(m32)} rows; undisturbed part {int(calm.sum())} rows) vs its own "
          "undisturbed part and vs trial 02 (eq. 40):\n")
    print("| method | 32 whole vs 32 undisturbed | 32 whole vs 02 | 32 undisturbed vs 02 | "
          "magnet-period samples flagged | undisturbed samples flagged |")
    print("|---|---|---|---|---|---|")
    magnet = (t32 >= 38.0) & (t32 <= 95.0)
    verdict = None
    for label, kw in cols.items():
        whole, part = Fitted(m32, "broad32", **kw), Fitted(m32[calm], "broad32 undisturbed", **kw)
        ref02 = Fitted(b02, "broad02", **kw)
        flags = ["", ""]
        if label == "autocal" and whole.cal is not None:
            flags = [f"{(~whole.cal.inliers[magnet]).mean():.1%}", f"{(~whole.cal.inliers[calm]).mean():.1%}"]
            verdict = whole.dev(part)
        print(f"| {label} | {cell(whole.dev(part), whole.mark(part))} | "
              f"{cell(whole.dev(ref02), whole.mark(ref02))} | {cell(part.dev(ref02), part.mark(ref02))} | "
              f"{flags[0]} | {flags[1]} |")
    if verdict is not None:
        print(f"\nTarget autocal BROAD 32 whole within 2 % of its undisturbed part: "
              f"{100 * verdict:.2f}% → {'PASS' if verdict <= 0.02 else 'FAIL'}")


def part_c() -> None:
    tracks = {s: real_track(f"tiva_mpu9250_mag_{s}").mag for s in TIVA}
    test = tracks[TIVA_REF]
    cols = all_variants()
    dev, err, secs, split, radius = {}, {}, {}, {}, {}
    for label, kw in cols.items():
        fits = {}
        t0 = time.perf_counter()
        for s in TIVA:
            fits[s] = Fitted(tracks[s], f"tiva_{s}", **kw)
        secs[label] = (time.perf_counter() - t0) / len(TIVA)
        ref = fits[TIVA_REF]
        dev[label] = {s: (fits[s].dev(ref), fits[s].mark(ref)) for s in TIVA if s != TIVA_REF}
        split[label] = {s: scale_free(fits[s], ref) for s in TIVA if s != TIVA_REF}
        radius[label] = {s: (np.nan if fits[s].cal is None else float(np.cbrt(np.linalg.det(fits[s].cal.K))))
                         for s in TIVA}
        err[label] = {}
        for s in TIVA:
            c = fits[s].cal
            e = np.nan if c is None else float(np.sqrt(np.mean(estimation_error(c.K, c.b, test) ** 2)))
            err[label][s] = (e, fits[s].mark())
    others = [s for s in TIVA if s != TIVA_REF]
    print(f"\n### (c) Table IV analogue: tiva_mpu9250_mag_* deviation (eq. 40) from each method's "
          f"fit on session {TIVA_REF}\n")
    print("| method | " + " | ".join(others) + " | mean s per fit |")
    print("|---|" + "---|" * (len(others) + 1))
    for label in cols:
        print(f"| {label} | " + " | ".join(cell(*dev[label][s], digits=1) for s in others)
              + f" | {secs[label]:.3f} |")
    print(f"\n### (c) Table V analogue: average sensor estimation error (eq. 41, counts) on session "
          f"{TIVA_REF} of the model learnt on each session\n")
    print("| method | " + " | ".join(TIVA) + " |")
    print("|---|" + "---|" * len(TIVA))
    for label in cols:
        row = []
        for s in TIVA:
            e, mk = err[label][s]
            row.append(("fail" if not np.isfinite(e) else f"{e:.2f}") + mk)
        print(f"| {label} | " + " | ".join(row) + " |")
    print(f"\n### (c) The same deviation split: shape of K (K / det(K)^⅓, eq. 40 on it) / hard-iron "
          f"offset ‖b − b_ref‖ in field radii, vs session {TIVA_REF}\n")
    print("| method | " + " | ".join(others) + " |")
    print("|---|" + "---|" * len(others))
    for label in cols:
        print(f"| {label} | " + " | ".join(
            "fail" if not np.isfinite(split[label][s][0]) else
            f"{100 * split[label][s][0]:.1f}% / {100 * split[label][s][1]:.1f}%" for s in others) + " |")
    print("\nField radius det(K)^⅓ (counts) per session, autocal: "
          + ", ".join(f"{s}: {radius['autocal'][s]:.1f}" for s in TIVA))
    lengths = ", ".join(f"{s}: {len(tracks[s])}" for s in TIVA)
    print(f"\nSamples per session: {lengths}.")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", choices=("a", "b", "c"), action="append")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    parts = args.part or ["a", "b", "c"]
    print(run_stamp())
    print("\n`*` = refused by the coverage check, refitted with check_coverage=False.")
    t0 = time.perf_counter()
    if "a" in parts:
        part_a(args.seed)
    if "b" in parts:
        part_b()
    if "c" in parts:
        part_c()
    if FAILURES:
        print("\nFailures (`fail` cells):\n")
        for line in FAILURES:
            print(f"- {line}")
    print(f"\n(total {time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
