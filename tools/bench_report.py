"""Benchmark: rendering every report figure (and the HTML page) for a 5-minute simulated track,
beside the diagnosis of the same track timed in the same run.

    python tools/bench_report.py [--duration 300] [--seed 0] [--repeat 3]

Target: all figures in a few seconds. Prints the times and the ratio figures / diagnosis.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=300.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=3, help="renders timed (best is reported)")
    args = parser.parse_args()

    from streamcal.diagnosis import diagnose
    from streamcal.report import FigureData, render_figures, render_html
    from streamcal.sim import simulate

    track = simulate(args.duration, args.seed, effects={"temperature_offset": 0.5},
                     outlier_bursts=1).track
    t0 = time.perf_counter()
    d = diagnose(track)
    t_diag = time.perf_counter() - t0
    render_figures(FigureData.build(track, d))          # warm-up: imports, font cache
    figs, pages = [], []
    for _ in range(max(1, args.repeat)):
        t0 = time.perf_counter()
        rendered = render_figures(FigureData.build(track, d))
        figs.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        page = render_html(track, d, figures=rendered)
        pages.append(time.perf_counter() - t0)
    t_fig, t_page = min(figs), min(pages)
    size = sum(len(f.png) for f in rendered)
    print(f"track: {args.duration:.0f} s, {d.n} magnetometer samples; verdict {d.verdict}, "
          f"top candidate {d.candidates[0].effect if d.candidates else '-'}")
    print(f"diagnosis            {t_diag:8.2f} s   (baseline)")
    print(f"{len(rendered)} figures (PNG)      {t_fig:8.2f} s   ({t_fig / t_diag:.2f} × the diagnosis; "
          f"target a few seconds: {'met' if t_fig <= 5 else 'NOT met'}); {size / 1e3:.0f} kB")
    print(f"HTML page from them  {t_page:8.3f} s   ({len(page) / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
