"""Without the real recordings a run skips their tests and ends with one line that counts them and
says how to run them (also under pytest-xdist); with ``CI`` set the same tests fail instead.

A tiny suite in a temporary folder loads this project's tests/conftest.py as a plugin, so it
gets the same fixtures and the same terminal summary as the real suite."""
from __future__ import annotations

import ast
import os
import re
import subprocess
import sys

import pytest

from .conftest import REPO, SHARED_ENV

TINY_SUITE = '''
import pytest
from tests.conftest import real_flight, real_track

def test_needs_tracks(real_tracks_dir):
    assert real_tracks_dir.is_dir()

def test_needs_flights(flight_dir):
    assert flight_dir.is_dir()

def test_needs_one_track():
    real_track("tiva_mpu9250_mag_06.csv")

def test_needs_one_flight():
    real_flight("px4_pyulog_sample.ulg")

def test_skips_for_another_reason():
    pytest.skip("no toolchain here")

def test_runs_anywhere():
    assert 1 + 1 == 2
'''


def _run(tmp_path, *flags, ci: bool = False) -> subprocess.CompletedProcess:
    suite = tmp_path / "suite"
    suite.mkdir(exist_ok=True)
    (suite / "test_tiny.py").write_text(TINY_SUITE)
    (suite / "pytest.ini").write_text("[pytest]\n")
    empty = tmp_path / "no-data"
    empty.mkdir(exist_ok=True)
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "PYTEST_ADDOPTS")}
    env[SHARED_ENV] = str(empty)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    if ci:
        env["CI"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "tests.conftest", "-p", "no:cacheprovider",
         "--rootdir", str(suite), *flags, str(suite)],
        capture_output=True, text=True, env=env, cwd=suite, timeout=240)


def _summary_lines(out: str) -> list[str]:
    return [line for line in out.splitlines() if "real-data test" in line]


@pytest.mark.parametrize("flags", [("-p", "no:xdist"), ("-n", "2")], ids=["serial", "xdist"])
def test_one_line_counts_only_the_real_data_skips_and_names_the_option(tmp_path, flags):
    proc = _run(tmp_path, *flags)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "1 passed, 5 skipped" in proc.stdout
    lines = _summary_lines(proc.stdout)
    assert len(lines) == 1, proc.stdout
    # four tests skip for missing data; the fifth skipped for another reason is not counted
    assert lines[0].startswith("4 real-data tests skipped")
    assert f"{SHARED_ENV}=DIR" in lines[0] and str(tmp_path / "no-data") in lines[0]


def test_each_skip_reason_names_the_missing_path_and_the_option(tmp_path):
    proc = _run(tmp_path, "-p", "no:xdist", "-rs")
    reasons = [line for line in proc.stdout.splitlines()
               if line.startswith("SKIPPED") and "real recordings not found" in line]
    assert len(reasons) == 4, proc.stdout
    assert all(f"{SHARED_ENV}=DIR" in r and str(tmp_path / "no-data") in r for r in reasons)


def test_in_ci_missing_data_fails_and_nothing_is_counted_as_skipped(tmp_path):
    proc = _run(tmp_path, "-n", "2", ci=True)
    assert proc.returncode == 1
    # a missing fixture directory is an error at set-up, a missing file a failure in the test
    assert "2 failed, 1 passed, 1 skipped, 2 errors" in proc.stdout
    assert "CI must have the real recordings" in proc.stdout
    assert _summary_lines(proc.stdout) == []


REAL = {"real_tracks_dir", "flight_dir", "real_data_dir"}
REAL_CALLS = {"real_path", "real_track", "real_flight"}


def _real_data_tests(source: str) -> set[str]:
    """Names of the tests in ``source`` that need the real recordings: they take a real-data
    fixture (directly or through a fixture of the module), or call a real_* helper (directly or
    through a helper of the module)."""
    tree = ast.parse(source)
    funcs = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}

    def needs(name: str, seen: frozenset = frozenset()) -> bool:
        node = funcs.get(name)
        if node is None or name in seen:
            return False
        seen = seen | {name}
        args = {a.arg for a in node.args.args}
        calls = {c.func.id for c in ast.walk(node)
                 if isinstance(c, ast.Call) and isinstance(c.func, ast.Name)}
        return bool(args & REAL or calls & REAL_CALLS) or any(
            needs(other, seen) for other in (args | calls) if other != name)

    return {name for name in funcs if name.startswith("test_") and needs(name)}


def test_every_real_data_test_is_in_the_table_of_docs_testing_md():
    """docs/testing.md names, for each real-data test, the simulated test of its behaviour."""
    table = (REPO / "docs" / "testing.md").read_text(encoding="utf-8")
    found = {}
    for path in sorted((REPO / "tests").glob("test_*.py")):
        if path.name.startswith("test_sim_"):
            continue
        for name in _real_data_tests(path.read_text(encoding="utf-8")):
            found[name] = path.name
    assert len(found) > 60                       # the scan itself works
    # a test is named in the table, or its whole file is, with a count: "`test_x.py` (six tests)"
    missing = sorted(f"{f}::{n}" for n, f in found.items()
                     if not re.search(rf"\b{n}\b", table) and f"`{f}` (" not in table)
    assert not missing, missing
