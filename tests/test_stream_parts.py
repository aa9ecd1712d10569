"""The calibrator's parts through their public surface: monotone clock, fit worker, recall."""
import threading

import numpy as np

from streamcal.calibration import Calibration
from streamcal.stream.clock import MonotoneClock
from streamcal.stream.fitworker import FitJob, FitWorker, SynchronousExecutor
from streamcal.stream.recall import Recaller


def test_clock_continues_after_a_jump_back():
    clock, events = MonotoneClock(), []
    a = clock.stamp(np.arange(0.0, 1.0, 0.1), events)
    b = clock.stamp(np.arange(0.0, 0.5, 0.1), events)       # the board restarted
    assert not np.any(np.diff(np.concatenate([a, b])) <= 0)
    assert len(events) == 1 and events[0].kind == "clock_reset"
    assert clock.shift == events[0].data["shift"] and clock.t_last == b[-1]
    other = MonotoneClock()
    other.adopt(clock)
    assert other.stamp(np.array([0.5]), [])[0] == 0.5 + clock.shift


def _job():
    return FitJob(fit_set="snap", holdout=None, coverage=0.5, t=1.0, support=None)


def test_synchronous_worker_runs_the_fit_at_once_and_keeps_errors():
    worker = FitWorker(lambda snap: f"fitted {snap}", synchronous=True)
    job = worker.submit(_job())
    assert job.done and job.result == "fitted snap" and job.error is None
    job = FitWorker(lambda snap: 1 / 0, synchronous=True).submit(_job())
    assert job.done and isinstance(job.error, ZeroDivisionError) and job.result is None
    assert SynchronousExecutor().submit(max, 2, 3).result() == 3


def test_thread_worker_does_not_block_the_caller():
    release = threading.Event()

    def fitter(snap):
        release.wait(5.0)
        return snap

    worker = FitWorker(fitter)
    job = worker.submit(_job())
    assert not job.done and not job.wait(0.01)     # the caller went on while it runs
    release.set()
    assert job.wait(5.0) and job.result == "snap"
    worker.shutdown()


def test_recaller_needs_consecutive_checks_and_restarts():
    cal = Calibration(K=50.0 * np.eye(3), b=np.array([5.0, 0.0, 0.0]), rms=0.5)
    rec = Recaller(window=40, remember=2, checks=3, drift_limit=lambda rms, R: 0.05)
    rec.remember(cal, None)
    rng = np.random.default_rng(0)

    def on(cal_b, n=10, t0=0.0):
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        return 50.0 * d + cal_b, t0 + 0.01 * np.arange(n)

    found = [rec.observe(*on(cal.b, t0=k)) for k in range(4)]     # the first full window
    assert found == [None] * 4
    found = [rec.observe(*on(cal.b, t0=4 + k)) for k in range(2)]  # 2nd and 3rd check
    assert found[0] is None and found[1] is not None
    assert found[1].calibration is cal and found[1].stat <= found[1].limit == 0.05
    rec.restart()
    assert all(rec.observe(*on(np.array([40.0, 0, 0]), t0=k)) is None for k in range(12))
    assert len(rec.remembered) == 1 and rec.capacity == 2


def test_reference_holds_back_beyond_its_limit_on_its_support_and_gross_anywhere():
    from streamcal.stream.coverage import CoverageBuffer
    from streamcal.stream.disturbance import GROSS
    from streamcal.stream.reference import Reference, beyond

    cells = CoverageBuffer().cells
    d = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    support = np.zeros(cells.n_cells, dtype=bool)
    support[cells.cell_of(d[:1])] = True                  # fitted on the +x direction only
    for hold in (True, False):
        ref = Reference(np.zeros(3), np.eye(3) / 50.0, 50.0, 0.5, 0.1, support, None, hold)
        scale = np.array([1.2, 1.2, 1.0 + GROSS + 0.1])   # +x, +y beyond the limit; z gross
        y = ref.project(50.0 * d * scale[:, None], None, None, ())
        held, err, inside, dirs, cell = beyond(y, ref, cells)
        np.testing.assert_allclose(err, scale - 1.0)
        np.testing.assert_array_equal(inside, [True, False, False])
        np.testing.assert_array_equal(held, [True, False, hold])
        np.testing.assert_allclose(dirs, d)
