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


# -- the disturbance tracker and the running sphere estimate ------------------------------------
def _sphere_samples(rng, n, center=(0.0, 0.0, 0.0), R=50.0):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    return R * d + np.asarray(center)


def _drive(tracker, policy, ref, cells, m, t, chunk=50):
    """Feed samples in chunks the way the calibrator does, up to the first environment change
    (the calibrator then forgets and judges against another reference); returns the events and
    the changes."""
    events, changes = [], []
    for k in range(0, len(m), chunk):
        mk, tk = m[k:k + chunk], t[k:k + chunk]
        held, err, inside, d, cell = tracker.disagreeing(mk, tk, np.empty((len(mk), 0)), ref,
                                                         (), cells)
        policy.observe(err[inside], tk[inside])
        check = policy.check(ref.rms, ref.radius)
        if check is not None:
            change = tracker.judge(check, ref, float(tk[-1]), events)
            if change is not None:
                changes.append(change)
                break
    return events, changes


def _tracker_setup():
    from streamcal.stream.coverage import CoverageBuffer
    from streamcal.stream.policy import RecalPolicy
    from streamcal.stream.reference import Reference
    from streamcal.stream.tracker import DisturbanceTracker

    policy = RecalPolicy()
    ref = Reference(np.zeros(3), np.eye(3) / 50.0, 50.0, 0.5, policy.drift_limit(0.5, 50.0),
                    None, None, True)
    return DisturbanceTracker(hold=4096, window=policy.window), policy, ref, \
        CoverageBuffer().cells


def test_tracker_calls_a_passing_phone_a_transient():
    tracker, policy, ref, cells = _tracker_setup()
    rng = np.random.default_rng(1)
    fs, n = 100.0, 3000
    t = np.arange(n) / fs
    m = _sphere_samples(rng, n)
    phone = (t > 10.0) & (t < 12.0)                   # two seconds of a strong extra field
    m[phone] += [40.0, 0.0, 0.0]
    events, changes = _drive(tracker, policy, ref, cells, m, t)
    assert changes == []
    kinds = [e for e in events if e.kind == "disturbance"]
    assert len(kinds) == 1 and kinds[0].data["outcome"] == "transient"
    assert 9.5 < kinds[0].data["start"] < 10.5 and kinds[0].data["held"] >= 150
    assert tracker.open is None and tracker.n_held >= 150


def test_tracker_calls_a_new_hard_iron_an_environment_change():
    tracker, policy, ref, cells = _tracker_setup()
    rng = np.random.default_rng(2)
    fs, n = 100.0, 3000
    t = np.arange(n) / fs
    m = _sphere_samples(rng, n)
    after = t >= 10.0
    shift = np.array([0.0, 15.0, 0.0])                # a magnet stuck to the board: 0.3 R
    m[after] += shift
    events, changes = _drive(tracker, policy, ref, cells, m, t)
    assert len(changes) == 1
    change = changes[0]
    assert 9.5 < change.onset < 10.5 and "one shell" in change.why
    held_m, held_t, held_cov = change.held
    assert len(held_t) > 100 and held_t.min() >= change.onset and held_cov.shape[1] == 0
    drift = [e for e in events if e.kind == "drift"]
    assert len(drift) == 1 and drift[0].data["reason"] == "new_shell"
    np.testing.assert_allclose(drift[0].data["hard_iron_shift"], shift, atol=1.0)
    assert tracker.open is None                       # cleared for the calibrator to go on


def test_running_sphere_frames_judges_and_refuses_a_cluster():
    from streamcal.stream.policy import RecalPolicy
    from streamcal.stream.running_sphere import RunningSphere, sphere_of_samples

    rng = np.random.default_rng(3)
    center, R = np.array([10.0, -5.0, 3.0]), 50.0
    sphere = RunningSphere(every=100, min_n=50)
    m = _sphere_samples(rng, 100, center, R) + rng.normal(scale=0.2, size=(100, 3))
    assert sphere.refit() == (None, False)            # nothing in the sums yet
    assert sphere.add(m)                               # a refit is due after 100 samples
    (c, r), moved = sphere.refit()
    assert moved and np.linalg.norm(c - center) < 0.5 and abs(r - R) < 0.5
    assert sphere.refit()[1] is False                  # the same sums: it did not move
    occupied = np.ones(8, dtype=bool)
    ref = sphere.judge_reference(m, occupied, RecalPolicy().drift_limit)
    assert ref is not None and not ref.hold and ref.radius == r
    cal = sphere.calibration("uT")
    np.testing.assert_allclose(cal.K, r * np.eye(3))
    np.testing.assert_allclose(cal.b, c)
    # A board at rest: a sphere through its noise cluster does not fit the cluster well enough
    # to judge anything.
    still = np.tile(center + [R, 0, 0], (200, 1)) + rng.normal(scale=0.2, size=(200, 3))
    sphere.reset(still)
    assert sphere.add(still)
    found, _ = sphere.refit()
    assert found is None or sphere.judge_reference(still, occupied,
                                                   RecalPolicy().drift_limit) is None
    assert sphere_of_samples(still[:10], 50) is None     # too few samples
    sphere.reset(m[:10])
    assert sphere.n == 10 and sphere.estimate is None and sphere.reference is None
