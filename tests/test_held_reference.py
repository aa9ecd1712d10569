"""The held refinement fitted against the attitude reference beside the field's magnitude
(streamcal.diagnosis.held.reference_rows): where a log has an attitude and a place, a refinement
no longer turns the heading the magnitude cannot see; without them nothing changes."""
import json

import numpy as np

from streamcal.calibration import Calibration, canonical_form
from streamcal.diagnosis.against import diagnose_against, refine
from streamcal.diagnosis.held.reference_rows import JointBlock, reference_rows
from streamcal.fitting.attitude_reference import fit_attitude_reference
from streamcal.fitting.entries import shifted
from streamcal.fitting.heading_check import heading_check
from streamcal.sim.flight import simulated_log

from .test_heading_check import _run

S_TRUE = np.array([[1.05, 0.03, -0.02], [0.03, 0.97, 0.04], [-0.02, 0.04, 1.02]])
B_TRUE = np.array([12.0, -7.0, 20.0])
CORE = ["K_xx", "K_xy", "K_xz", "K_yy", "K_yz", "K_zz", "b_x", "b_y", "b_z"]


def _calibration(field, S, b, source):
    """A firmware-like calibration: body direction to reading ``field · S`` (S symmetric)."""
    K, Q = canonical_form(field * S)
    return Calibration(K=K, b=b, model=("hard_iron", "soft_iron"), field=field, unit="uT",
                       extra={"frame_rotation_Q": Q.tolist(), "source": source})


def _level_flight():
    """A nearly level flight turning through half a circle of heading (the magnitude leaves
    the vertical and the cross terms to the calibration held), its true calibration, and a held
    one off in scale, soft iron and offset."""
    track, truth = simulated_log("flight", duration_s=120, S=S_TRUE, b_body=B_TRUE, seed=5,
                                 tilt_deg=5.0, noise_uT=0.1, turns=0.5)
    field = float(np.linalg.norm(truth["b_ned"]))
    off = np.array([[-0.06, 0.04, 0.03], [0.04, 0.07, -0.03], [0.03, -0.03, 0.08]])
    return (track, _calibration(field, S_TRUE, B_TRUE, "truth"),
            _calibration(field, S_TRUE + off, B_TRUE + [3.0, -3.0, -6.0], "given"))


def test_magnitude_only_turns_the_heading_the_joint_fit_recovers_the_truth():
    track, true, given = _level_flight()
    truth_deg = heading_check(track, true, true)["rms_after"]
    magnitude = refine(track, given, [], attitude=False)
    joint = refine(track, given, [])
    h_mag = heading_check(track, true, magnitude)["rms_after"]
    h_joint = heading_check(track, true, joint)["rms_after"]
    assert h_mag > truth_deg + 1.0            # the magnitude alone turns the heading
    assert h_joint <= truth_deg + 0.05        # the joint fit points as the truth does
    assert "attitude_reference_used" not in (magnitude.extra or {})
    assert np.max(np.abs(joint.b - B_TRUE)) < 0.5
    assert np.max(np.abs(magnitude.b - B_TRUE)) > 2.0
    # more is determined with the attitude, and the field's magnitude is fitted as well
    assert len(joint.extra["held"]) < len(magnitude.extra["held"])
    assert joint.rms <= 1.05 * magnitude.rms
    used = joint.extra["attitude_reference_used"]
    assert used["samples"] == heading_check(track, given, joint)["n"] and used["caveat"]


def test_the_block_gradient_is_the_derivative_of_its_cost():
    """At the truth (small residuals: the Gauss–Newton rows hold the tangents fixed)."""
    track, true, _ = _level_flight()
    ref = reference_rows(track, true)[0].scaled(50.0)
    cov = {k: np.asarray(v, float) for k, v in track.covariates_at_mag().items()}
    block = JointBlock(ref, track.mag, cov, tau=0.25, n_held=0)
    _, _, grad = block.linearize(CORE, true.K, true.b, [])
    numeric = []
    for k in range(len(CORE)):
        step = np.zeros(len(CORE))
        step[k] = 1e-4
        up, down = shifted(true.K, true.b, CORE, step), shifted(true.K, true.b, CORE, -step)
        numeric.append((block.cost(*up, []) - block.cost(*down, [])) / 2e-4)
    # the block's gradient carries (τ/τ_r)² and leaves out the cost's 2/τ²
    analytic = 2 * grad / block.scale / block.tau_ref ** 2
    assert np.allclose(analytic, numeric, rtol=0.02, atol=1e-3 * np.max(np.abs(numeric)))


def test_reference_rows_on_a_subsample_are_the_same_samples():
    track, _, given = _level_flight()
    ref = reference_rows(track, given)[0]
    rows = np.arange(0, len(track.mag), 3)
    sub = ref.at(rows)
    assert np.array_equal(rows[sub.index], ref.index[np.isin(ref.index, rows)])
    assert np.allclose(sub.body, ref.body[np.isin(ref.index, rows)])


def test_without_a_place_the_refinement_is_the_magnitude_one():
    track, _, given = _level_flight()
    for key in [k for k in track.metadata if k.startswith("gps_")]:
        track.metadata.pop(key)
    assert reference_rows(track, given)[0] is None
    a, b = refine(track, given, []), refine(track, given, [], attitude=False)
    assert a.to_dict() == b.to_dict()
    d = diagnose_against(track, given)
    assert not d.held.attitude_reference and "held_attitude_reference" not in d.to_dict()


def test_a_mounting_the_calibration_does_not_describe_is_not_used():
    track, _, given = _level_flight()
    turned = given.replace(extra={**given.extra, "frame_rotation_Q": np.diag([-1.0, -1.0, 1.0])
                                  .tolist()})
    rows, why = reference_rows(track, turned)
    assert rows is None and "points" in why


def test_a_place_given_on_the_command_line_is_in_the_pasted_command(tmp_path):
    """A log without GPS, the place given as --lat/--lon/--date: the diagnosis' held fit uses
    the attitude reference there, the pasted command carries the place and gives the promise."""
    gain = np.array([0.6, -0.4, 0.3])
    track, _ = simulated_log("flight", duration_s=120, S=S_TRUE, b_body=B_TRUE,
                             current_gain=gain, seed=4)
    cal = fit_attitude_reference(track, channels=())
    cal.save(tmp_path / "cal.json")
    lat, lon, date = track.metadata["gps_lat_deg"], track.metadata["gps_lon_deg"], \
        track.metadata["gps_date"]
    for key in [k for k in track.metadata if k.startswith("gps_")]:
        track.metadata.pop(key)
    path = tmp_path / "flight.csv"
    track.write(path)
    d = json.loads(_run("diagnose", str(path), "--cal", str(tmp_path / "cal.json"), "--lat", lat,
                        "--lon", lon, "--date", date, "--json").stdout)
    used = d["held_attitude_reference"]
    assert used["samples"] == d["heading_check"]["n"]
    step = d["next_step"]
    assert step and step[step.index("--lat") + 1] == repr(float(lat)) and "--date" in step
    argv = [a if a != "refined.json" else str(tmp_path / "r.json") for a in step[1:]]
    out = _run(*argv).stdout
    assert "attitude  fitted with the field's direction" in out and "caveat" in out
    saved = json.loads((tmp_path / "r.json").read_text())
    assert saved["attitude_reference_used"] == used
    assert saved["heading_check"] == d["heading_check"]
    assert abs(saved["rms"] - d["ladder"][-1]["rms"]) <= 0.01 * d["ladder"][-1]["rms"]
    # without the place: the magnitude alone, and the command says no place
    plain = json.loads(_run("diagnose", str(path), "--cal", str(tmp_path / "cal.json"),
                            "--json").stdout)
    assert "held_attitude_reference" not in plain and "--lat" not in (plain["next_step"] or [])


def test_candidates_ranked_on_a_subsample_use_the_reference_there():
    track, _, given = _level_flight()
    whole = diagnose_against(track, given)
    sub = diagnose_against(track, given, rank_max=400)
    assert sub.held.n_ranked < len(track.mag) == whole.held.n_ranked
    assert sub.held.attitude_reference == whole.held.attitude_reference
    # the base is fitted on every sample either way: the same held fit
    assert sub.held.estimated == whole.held.estimated
    assert {c.effect for c in sub.candidates} == {c.effect for c in whole.candidates}


def test_the_report_says_the_held_fit_used_the_attitude():
    """The report's held section says the held fits also fitted the direction against the
    attitude reference (samples, width, caveat) — and says nothing of it when they did not."""
    from streamcal.report.held_table import held_section

    track, _, given = _level_flight()
    joint = diagnose_against(track, given, ladder=False)
    page = held_section(joint, "µT")
    used = joint.held.attitude_reference
    assert used and f"against the attitude reference ({used['samples']} samples" in page
    assert "steered by the compass" in page
    alone = diagnose_against(track, given, ladder=False, attitude=False)
    assert not alone.held.attitude_reference
    assert "attitude reference" not in held_section(alone, "µT")
