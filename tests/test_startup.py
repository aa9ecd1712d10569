"""Startup (issue #12 item 7): the services load neither matplotlib, nor cvxpy, nor scipy.signal
before their first samples (a Raspberry Pi is about 10× slower than this machine; the fit
worker may import a solver when the first fit runs)."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
BENCH = REPO / "tools" / "bench_startup.py"
FORBIDDEN = ("matplotlib", "cvxpy", "scipy.signal")


def _forbidden_in(modules) -> list:
    return sorted(m for m in modules if any(m == f or m.startswith(f + ".") for f in FORBIDDEN))


@pytest.mark.parametrize("command", ["daemon", "record", "serial"])
def test_service_commands_do_not_load_plotting_or_solvers(command):
    res = subprocess.run([sys.executable, str(BENCH), "--probe", command], capture_output=True,
                         text=True, cwd=REPO, timeout=300)
    assert res.returncode == 0, res.stderr
    found = json.loads(res.stdout)
    assert found["exit"] == 0
    assert len(found["modules"]) > 50                     # the command really ran
    if command != "record":
        assert found["samples"] > 0                        # …and took samples
    assert _forbidden_in(found["modules"]) == []


def test_calibrator_and_command_modules_import_light():
    code = ("import sys, json\n"
            "import streamcal.cli.daemon, streamcal.cli.record, streamcal.cli.serial\n"
            "import streamcal.service\n"
            "from streamcal.stream.calibrator import StreamingCalibrator\n"
            "from streamcal.report.terminal import coverage_view\n"
            "StreamingCalibrator()\n"
            "print(json.dumps(list(sys.modules)))\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, timeout=300)
    assert res.returncode == 0, res.stderr
    modules = json.loads(res.stdout)
    assert "streamcal.stream.calibrator" in modules
    assert _forbidden_in(modules) == []
