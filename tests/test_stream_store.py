"""CalibrationStore: atomic current file, bounded history, fallback, permissions, symlinks,
and survival of a writer killed with SIGKILL at random instants."""
import os
import random
import signal
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.errors import InputError
from streamcal.stream.store import CalibrationStore

REPO = Path(__file__).resolve().parent.parent


def _cal(k):
    return Calibration(K=np.diag([50.0 + k, 48.0, 52.0]), b=[k, -2.0, 3.0], rms=0.4, n=100 + k)


def test_save_load_and_bounded_history(tmp_path):
    store = CalibrationStore(tmp_path / "state", keep=3)
    assert store.load().calibration is None
    for k in range(5):
        store.save(_cal(k))
    result = store.load()
    assert result.path == store.current_path and not result.problems
    assert result.calibration.n == 104
    assert [p.name for p in store.history()] == ["0003.json", "0004.json", "0005.json"]


def test_permissions(tmp_path):
    store = CalibrationStore(tmp_path / "state")
    store.save(_cal(1))
    assert stat.S_IMODE(os.stat(store.dir).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(store.history_dir).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(store.current_path).st_mode) == 0o600
    assert all(stat.S_IMODE(os.stat(p).st_mode) == 0o600 for p in store.history())


def test_damaged_current_falls_back_to_newest_good_history(tmp_path):
    store = CalibrationStore(tmp_path / "state")
    for k in range(3):
        store.save(_cal(k))
    store.history()[-1].write_text("{ torn")               # newest history damaged too
    store.current_path.write_text('{"format": "something-else/9"}')
    result = store.load()
    assert result.fell_back and result.path.name == "0002.json" and result.calibration.n == 101
    assert len(result.problems) == 2
    assert "format" in result.problems[0] and "not valid JSON" in result.problems[1]


def test_refuses_symlinks(tmp_path):
    real = tmp_path / "real"
    real.mkdir()
    link = tmp_path / "link"
    link.symlink_to(real)
    with pytest.raises(InputError, match="symbolic link"):
        CalibrationStore(link)
    store = CalibrationStore(tmp_path / "state")
    target = tmp_path / "elsewhere.json"
    _cal(7).save(target)
    store.current_path.symlink_to(target)
    result = store.load()
    assert result.calibration is None and "symbolic link" in result.problems[0]
    with pytest.raises(InputError):
        store.save(_cal(8))                               # would write through the link
    assert Calibration.load(target).n == 107


_WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    from streamcal.calibration import Calibration
    from streamcal.stream.store import CalibrationStore

    store = CalibrationStore(sys.argv[1], keep=5)
    k = 0
    while True:
        k += 1
        store.save(Calibration(K=np.diag([50.0 + k % 7, 48.0, 52.0]), b=[k, 0.0, 0.0],
                               rms=0.5, n=k))
        if k == 1:
            print("ready", flush=True)
""")


@pytest.mark.slow
def test_survives_sigkill_mid_write(tmp_path):
    state = tmp_path / "state"
    rng = random.Random(1234)
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    last_n = 0
    for _ in range(30):
        proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(state)], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
            time.sleep(rng.uniform(0.0, 0.05))
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        assert proc.returncode == -signal.SIGKILL
        result = CalibrationStore(state, keep=5).load()
        assert result.path.name == "calibration.json" and not result.problems
        assert result.calibration.n >= 1
        last_n = result.calibration.n
    assert last_n >= 1
    assert len(CalibrationStore(state, keep=5).history()) <= 6
