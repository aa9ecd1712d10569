"""Crash safety: a writer killed with SIGKILL at random instants never leaves a broken calibration.

A forked child writes calibrations in a tight loop (``Calibration.save`` or
``CalibrationStore.save``, each resuming from what the last one left on disk); the parent kills
it a random 1–30 ms after it is ready to write (longer on a machine too loaded for the writer to
finish a write in that time), many times over. After every kill: the file on disk is a valid
calibration, the old one or a newer one (never older than what was seen before), temp debris is
at most one file per interrupted write and is swept by the next write once stale, and a restart
(``CalibrationStore.load``) resumes from the current file.
"""
from __future__ import annotations

import os
import random
import select
import signal
import time

import numpy as np
import pytest

from streamcal.calibration import Calibration
from streamcal.stream.store import CalibrationStore

KILLS = 120
pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")


def _cal(n: int) -> Calibration:
    return Calibration(K=np.diag([50.0 + n % 7, 48.0, 52.0]), b=[float(n), -2.0, 3.0], rms=0.4,
                       n=n, coverage=0.9)


def _run_and_kill(child, delay_s: float) -> None:
    """Fork; the child runs ``child(ready)`` forever, calling ``ready()`` once it is about to
    write; SIGKILL it ``delay_s`` after that (the fork and the child's start-up are not counted,
    so a loaded machine still sees kills during the writes)."""
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - child
        try:
            os.close(read_end)
            child(lambda: os.write(write_end, b"r"))
        finally:
            os._exit(0)
    os.close(write_end)
    try:
        ready = select.select([read_end], [], [], 60.0)[0] and os.read(read_end, 1) == b"r"
    finally:
        os.close(read_end)
    if ready:
        time.sleep(delay_s)
    os.kill(pid, signal.SIGKILL)
    _, status = os.waitpid(pid, 0)
    assert ready, "the writer never got ready to write (did it crash?)"
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, \
        "the writer ended before it was killed (did it crash?)"


class _KillWindow:
    """Random kill delays, 1 ms up to ``hi``; ``hi`` doubles (to at most 1 s) after a run in which
    the writer finished no write, so that a slow or loaded machine still makes progress."""

    def __init__(self, seed: int, hi: float = 0.030):
        self.rng, self.hi = random.Random(seed), hi

    def delay(self) -> float:
        return self.rng.uniform(0.001, self.hi)

    def progressed(self, yes: bool) -> None:
        if not yes:
            self.hi = min(2 * self.hi, 1.0)


def _temps(directory) -> list[str]:
    return [e.name for e in os.scandir(directory) if e.name.startswith(".") and e.name.endswith(".tmp")]


@pytest.mark.slow
def test_calibration_save_killed_at_random_instants(tmp_path):
    path = tmp_path / "cal.json"
    _cal(1).save(path)
    window = _KillWindow(20240607)
    last_n, newer, debris_seen = 1, 0, 0

    def writer(ready):
        k = Calibration.load(path).n        # resume from what is on disk
        ready()
        while True:
            k += 1
            _cal(k).save(path)

    for _ in range(KILLS):
        _run_and_kill(writer, window.delay())
        cal = Calibration.load(path)        # raises if torn, foreign or invalid
        assert cal.n >= last_n, "an older calibration replaced a newer one"
        np.testing.assert_array_equal(cal.b, [cal.n, -2.0, 3.0])
        newer += cal.n > last_n
        window.progressed(cal.n > last_n)
        last_n = cal.n
        temps = _temps(tmp_path)
        debris_seen = max(debris_seen, len(temps))
        assert len(temps) <= KILLS           # at most one per interrupted write, never more
    assert newer >= KILLS // 2, f"the writer made progress in only {newer} of {KILLS} runs"
    left = _temps(tmp_path)
    assert set(os.listdir(tmp_path)) - set(left) == {"cal.json"}
    # the next save sweeps the leftovers once they are stale, and only those
    old = time.time() - 3600
    for name in left:
        os.utime(tmp_path / name, (old, old))
    (tmp_path / ".cal.json.inflight.tmp").write_bytes(b"{")           # a write in progress elsewhere
    (tmp_path / ".other.json.x.tmp").write_bytes(b"{")                # another file's leftover
    os.utime(tmp_path / ".other.json.x.tmp", (old, old))
    _cal(last_n + 1).save(path)
    assert sorted(_temps(tmp_path)) == [".cal.json.inflight.tmp", ".other.json.x.tmp"]
    print(f"\nCalibration.save: {KILLS} SIGKILLs, final n={last_n}, temp files left {len(left)}, "
          f"swept by the next save once stale")


@pytest.mark.slow
def test_calibration_store_killed_at_random_instants_then_restarts(tmp_path):
    state = tmp_path / "state"
    keep = 5
    CalibrationStore(state, keep=keep).save(_cal(1))
    window = _KillWindow(7)
    last_n, interrupted, longest, before = 1, 0, 0, 0

    def writer(ready):
        store = CalibrationStore(state, keep=keep)
        k = store.load().calibration.n      # a restart resumes from the current file
        ready()
        while True:
            k += 1
            store.save(_cal(k))

    for _ in range(KILLS):
        _run_and_kill(writer, window.delay())
        store = CalibrationStore(state, keep=keep)
        result = store.load()
        assert result.path == store.current_path and not result.problems, result.problems
        cal = result.calibration
        assert cal.n >= last_n
        window.progressed(cal.n > last_n)
        last_n = cal.n
        history = store.history()
        longest = max(longest, len(history))
        assert len(history) >= 1
        numbers = [Calibration.load(p).n for p in history]   # every history file is valid
        assert cal.n <= max(numbers)   # an interrupted save may have recorded a newer one
        temps = _temps(state) + _temps(store.history_dir)
        interrupted += len(temps) > before
        before = len(temps)
        assert len(temps) <= 2 * KILLS
    # Stale debris is swept by the next start; fresh debris (a write in progress) is left alone.
    old = time.time() - 3600
    for d in (state, state / "history"):
        for name in _temps(d):
            os.utime(d / name, (old, old))
    store = CalibrationStore(state, keep=keep)
    assert _temps(state) == [] and _temps(store.history_dir) == []
    assert store.load().calibration.n == last_n
    # Kills between a history write and its pruning leave extra history files; the next
    # completed save prunes them all.
    store.save(_cal(last_n + 1))
    assert len(store.history()) == keep
    print(f"\nCalibrationStore: {KILLS} SIGKILLs, final n={last_n}, {interrupted} kills left "
          f"new temp files (then swept); longest history seen {longest} files (keep={keep})")


def test_restart_prunes_history_left_by_interrupted_saves(tmp_path):
    keep = 3
    store = CalibrationStore(tmp_path / "state", keep=keep)
    for n in range(1, 4):
        store.save(_cal(n))
    # what several writers killed between history write and pruning leave behind
    for n in range(4, 9):
        (store.history_dir / f"{n:04d}.json").write_text(_cal(n).to_json())
    restarted = CalibrationStore(tmp_path / "state", keep=keep)
    assert len(restarted.history()) <= keep
    assert restarted.load().calibration.n == 3        # the current file is what is in use
