"""Startup cost of the long-running commands (issue #12 item 7): ``daemon``, ``record``, ``serial``.

For each command, in fresh subprocesses:

- ``help``: wall time of ``python -X importtime -m streamcal CMD --help`` (argument parsing only);
- ``run``: the command itself over ``fake:`` (the demo track) for a fraction of a second — long
  enough for its first samples, too short for a first fit — reporting the modules it loaded
  and which heavy ones (matplotlib, cvxpy, scipy.signal, …) are among them;
- ``import``: wall time of importing exactly the modules the run loaded, in a fresh interpreter;

each against the same-run baseline ``python -c "import numpy"`` (best of ``--repeat``).

    python3 tools/bench_startup.py [--repeat 3]
    python3 tools/bench_startup.py --probe daemon     # one run, JSON on stdout (tests use it)
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DEMO = REPO / "streamcal" / "data" / "demo_track.csv.gz"
COMMANDS = ("daemon", "record", "serial")
#: Modules a Raspberry Pi should not load to start a service (seconds each on a Pi 3).
HEAVY = ("matplotlib", "cvxpy", "scipy.signal", "scipy.stats", "scipy.optimize",
         "scipy.interpolate", "scipy.spatial", "scipy.linalg", "scipy", "dask", "pandas")
#: The run stops after this long (s of samples or of wall time): far below a first fit's needs
#: (35 % of the sphere).
RUN_SECONDS = 0.3


def command_argv(cmd: str, tmp: str) -> list[str]:
    """The command line probed: ``fake:`` source, private state dir, no socket."""
    if cmd == "daemon":
        return ["daemon", "--bus", f"fake:{DEMO}", "--state-dir", tmp, "--no-socket",
                "--max-seconds", str(RUN_SECONDS)]
    if cmd == "serial":
        return ["serial", "--port", f"fake:{DEMO}", "--state-dir", tmp, "--no-socket",
                "--max-seconds", str(RUN_SECONDS)]
    if cmd == "record":
        return ["record", "--bus", f"fake:{DEMO}", "-o", os.path.join(tmp, "rec.csv"),
                "--seconds", str(RUN_SECONDS)]
    raise ValueError(f"unknown command {cmd!r}")


def probe(cmd: str) -> dict:
    """Run ``cmd`` in this (fresh) process; the modules it loaded, in import order."""
    sys.path.insert(0, str(REPO))
    before = set(sys.modules)
    t0 = time.perf_counter()
    from streamcal.cli import main

    with tempfile.TemporaryDirectory() as tmp:
        import contextlib
        import io

        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            code = main(command_argv(cmd, tmp))
    loaded = [m for m in sys.modules if m not in before]
    samples = None
    for line in out.getvalue().splitlines()[::-1]:     # the services' summary line
        try:
            samples = json.loads(line).get("samples")
            break
        except (ValueError, AttributeError):
            continue
    return {"command": cmd, "exit": code, "seconds": time.perf_counter() - t0,
            "samples": samples, "modules": loaded,
            "heavy": [h for h in HEAVY if h in sys.modules]}


def run_probe(cmd: str) -> dict:
    """:func:`probe` in a fresh interpreter."""
    res = subprocess.run([sys.executable, __file__, "--probe", cmd], capture_output=True,
                         text=True, cwd=REPO, timeout=300)
    if res.returncode != 0:
        raise RuntimeError(f"probe {cmd} failed:\n{res.stderr}")
    return json.loads(res.stdout)


def _wall(argv: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, cwd=REPO, check=True, capture_output=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--probe", choices=COMMANDS)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if args.probe:
        print(json.dumps(probe(args.probe)))
        return
    py = sys.executable
    best = lambda argv: min(_wall(argv) for _ in range(args.repeat))  # noqa: E731
    base = best([py, "-c", "import numpy"])
    print(f"baseline python -c 'import numpy': {base:.3f} s (best of {args.repeat})")
    print(f"{'command':8} {'--help s':>9} {'×base':>6} {'import s':>9} {'×base':>6} "
          f"{'modules':>8}  heavy modules loaded")
    for cmd in COMMANDS:
        helptime = best([py, "-X", "importtime", "-m", "streamcal", cmd, "--help"])
        found = run_probe(cmd)
        # Only the package's own modules and what they pull in: importing each name again in
        # a fresh interpreter, in the order the command imported them.
        names = [m for m in found["modules"] if not m.startswith("__")]
        code = ("import importlib, sys\nsys.path.insert(0, %r)\n" % str(REPO)
                + "for n in %r:\n    try:\n        importlib.import_module(n)\n"
                  "    except Exception:\n        pass\n" % names)
        imp = best([py, "-c", code])
        heavy = ", ".join(found["heavy"]) or "none"
        print(f"{cmd:8} {helptime:9.3f} {helptime / base:6.2f} {imp:9.3f} {imp / base:6.2f} "
              f"{len(names):8d}  {heavy}")


if __name__ == "__main__":
    main()
