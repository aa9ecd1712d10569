"""Results are values (SPEC §5): a diagnosis and its candidates are frozen, compare equal when
their contents are (arrays element-wise, NaN equal to NaN), round-trip through JSON; a
calibration's ``created`` stamp takes no part in equality; Track, Calibration and Diagnosis show
as escaped HTML tables; ``dir``/``help`` list the public API."""
import copy
import dataclasses
import json
import pickle
import pydoc

import numpy as np
import pytest

import streamcal
from streamcal.calibration import jsonable
from streamcal.diagnosis.held.part import HeldPart
from streamcal.sim import simulate
from streamcal.sim.yaw_slice import yaw_slice
from streamcal.values import FrozenDict, freeze, same, thaw


@pytest.fixture(scope="module")
def fresh():
    """A fresh diagnosis of a full tumble with a hidden temperature offset."""
    sim = simulate(60.0, seed=1, effects={"temperature_offset": 0.3})
    return streamcal.diagnose(sim.track)


@pytest.fixture(scope="module")
def held():
    """A slice (yaw turns, ±10° tilt) diagnosed against the bench calibration of the same
    board."""
    full = simulate(60.0, seed=1, temp_profile="constant")
    cal = streamcal.fit(full.track)
    sl = yaw_slice(30.0, seed=1, K=full.truth.K, b=full.truth.b, tilt_deg=10)
    return streamcal.diagnose(sl.track, calibration=cal, calibration_source="bench.json")


def _json(d) -> dict:
    return json.loads(json.dumps(jsonable(d.to_dict()), allow_nan=False))


def test_one_type_the_held_part_optional(held, fresh):
    assert type(held) is type(fresh) is streamcal.Diagnosis
    assert isinstance(held.held, HeldPart) and held.held.parameters
    assert fresh.held is None and "held" not in fresh.to_dict()
    assert fresh.candidates and held.candidates


def test_diagnosis_and_candidates_are_frozen(fresh, held):
    for d in (fresh, held):
        with pytest.raises(dataclasses.FrozenInstanceError):
            d.verdict = "at_noise_floor"
        with pytest.raises(dataclasses.FrozenInstanceError):
            d.summary = ""
        with pytest.raises(dataclasses.FrozenInstanceError):
            d.candidates[0].significant = not d.candidates[0].significant
        with pytest.raises(ValueError):
            d.outliers[0] = not d.outliers[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        held.held = None
    with pytest.raises(dataclasses.FrozenInstanceError):
        held.held.parameters = ()


def _refuses_change(container) -> None:
    """``container`` (a tuple, mapping or array held by a value) cannot be changed in place."""
    if isinstance(container, np.ndarray):
        with pytest.raises(ValueError):
            container[...] = 0
    elif isinstance(container, tuple):
        with pytest.raises((TypeError, AttributeError)):
            container[0] = None   # noqa: tuple item assignment
        with pytest.raises(AttributeError):
            container.append(None)
    else:
        key = next(iter(container), "key")
        with pytest.raises(TypeError):
            container[key] = None
        with pytest.raises(TypeError):
            del container[key]
        for method in ("update", "pop", "clear", "setdefault"):
            assert not hasattr(container, method), method
    items = container.values() if hasattr(container, "values") else (
        container if isinstance(container, tuple) else ())
    for item in items:
        if isinstance(item, (tuple, FrozenDict, np.ndarray)) and len(item):
            _refuses_change(item)


CONTAINERS = ("candidates", "outlier_spans", "ladder", "residual_families", "noise", "misfit",
              "sampling", "next_step", "heading_error_deg", "model", "outliers_model")
HELD_CONTAINERS = ("parameters", "estimated", "predicted_sigma", "aux_channels", "fit_status",
                   "held_after_fit", "suspicious", "gyro_pinned", "gyro_link")


def test_every_container_refuses_in_place_change(fresh, held):
    long = fresh.replace(sampling={"samples_used": 10, "samples_total": 20,
                                   "subsample_rule": "rule", "outlier_spans_over": "subsample"},
                         outlier_spans=[[1.0, 2.0]])
    checked = set()
    for d in (long, held):
        for name in CONTAINERS:
            value = getattr(d, name)
            assert not isinstance(value, (list, dict)), name
            if value:
                _refuses_change(value)
                checked.add(name)
    assert checked == set(CONTAINERS)   # none was empty, so each was tried
    for name in HELD_CONTAINERS:
        value = getattr(held.held, name)
        assert not isinstance(value, (list, dict)), name
        if value:
            _refuses_change(value)
    assert held.held.parameters and held.held.estimated and held.held.fit_status
    step = held.ladder[0]
    assert step["rms"] == held.rms and step.get("added") is None   # read like a dict
    for c in (*fresh.candidates, *held.candidates):
        with pytest.raises(dataclasses.FrozenInstanceError):
            c.evidence = ""
        assert not any(isinstance(getattr(c, f.name), (list, dict))
                       for f in dataclasses.fields(c))


def test_containers_given_as_lists_are_frozen_and_not_shared(fresh):
    ladder = [dict(s) for s in thaw(fresh.ladder)]
    d = fresh.replace(ladder=ladder)
    ladder[0]["rms"] = -1.0
    ladder.append({})
    assert d == fresh and isinstance(d.ladder, tuple) and isinstance(d.ladder[0], FrozenDict)
    assert d.to_dict()["ladder"] == thaw(fresh.ladder)
    assert type(d.to_dict()["ladder"]) is list and type(d.to_dict()["ladder"][0]) is dict


def test_deepcopy_and_pickle_give_equal_frozen_values(fresh, held):
    for d in (fresh, held):
        for twin in (copy.deepcopy(d), pickle.loads(pickle.dumps(d))):
            assert twin == d and twin.held == d.held
            assert isinstance(twin.ladder[0], FrozenDict)
            _refuses_change(twin.ladder)
            _refuses_change(twin.noise)
    frozen = freeze({"a": [1.0, {"b": np.arange(3.0)}]})
    assert pickle.loads(pickle.dumps(frozen)) == frozen == copy.deepcopy(frozen)
    assert not pickle.loads(pickle.dumps(frozen))["a"][1]["b"].flags.writeable


def test_every_field_is_declared(fresh, held):
    # slots-like check: nothing beyond the declared fields lives on the values
    for value in (fresh, held, held.held, fresh.candidates[0], held.candidates[0]):
        declared = {f.name for f in dataclasses.fields(value)}
        assert set(vars(value)) <= declared, set(vars(value)) - declared


def test_equal_to_a_deep_copy_and_not_to_a_changed_one(fresh, held):
    for d in (fresh, held):
        twin = copy.deepcopy(d)
        assert d == twin and not d != twin
        assert d.candidates[0] == twin.candidates[0]
        assert d != d.replace(verdict="unexplained")
        assert d != d.replace(rms=d.rms * (1 + 1e-9))
        assert d != d.replace(candidates=d.candidates[1:])
        assert d.candidates[0] != d.candidates[0].replace(rms_after=d.candidates[0].rms_after / 2)
    assert fresh != held


def test_nan_is_equal_to_nan_where_it_means_no_value(fresh):
    unmeasured = fresh.replace(noise_floor=float("nan"), noise_floor_reliable=False,
                               rms=float("nan"))
    assert unmeasured == copy.deepcopy(unmeasured)
    assert unmeasured != fresh
    c = fresh.candidates[0].replace(p_value=float("nan"))
    assert c == copy.deepcopy(c) and c != fresh.candidates[0]


def test_replace_leaves_the_original_and_keeps_the_held_part(held):
    changed = held.replace(summary="other words")
    assert changed.held == held.held and changed.held.parameters == held.held.parameters
    assert held.summary != "other words"
    assert held != held.replace(held=dataclasses.replace(held.held,
                                                         tolerance=held.held.tolerance * 2))


@pytest.mark.parametrize("which", ["fresh", "held"])
def test_to_dict_from_dict_round_trip(which, request):
    d = request.getfixturevalue(which)
    again = streamcal.Diagnosis.from_dict(d.to_dict())
    assert again == d and type(again) is type(d)
    assert (again.held is None) == (d.held is None) == (which == "fresh")
    assert again.held == d.held
    through_json = streamcal.Diagnosis.from_dict(_json(d))
    assert through_json == d and type(through_json) is type(d)
    assert _json(through_json) == _json(d)
    # what the JSON does not carry is absent, and stated so
    assert again.outliers is None and again.calibration is None
    assert again.candidates[0].calibration is None
    assert [c.effect for c in again.candidates] == [c.effect for c in d.candidates]
    assert again.candidates == d.candidates
    assert str(again) == str(d) and repr(again) == repr(d)
    plain = d.to_dict()
    kept = streamcal.Diagnosis.from_dict(plain)
    plain["ladder"][0]["rms"] = -1.0                 # the value does not share the dict
    assert kept == d


def test_round_trip_of_a_diagnosis_with_no_floor(fresh):
    d = fresh.replace(noise_floor=float("nan"), noise_floor_reliable=False)
    again = streamcal.Diagnosis.from_dict(_json(d))
    assert again == d and np.isnan(again.noise_floor) and not again.floor_known


def test_calibration_equality_ignores_the_created_stamp(fresh):
    cal = fresh.calibration
    later = cal.replace(created="2001-02-03T04:05:06Z")
    assert later.created != cal.created
    assert later == cal and hash(later) == hash(cal)
    assert later.to_dict()["created"] == "2001-02-03T04:05:06Z"   # still saved
    assert later != cal.replace(rms=cal.rms * 1.001)
    again = streamcal.Calibration.from_json(later.to_json())
    assert again == cal
    assert streamcal.Calibration.from_dict(later.to_dict()) == cal


def test_calibration_from_dict_validates_like_load(fresh):
    bad = fresh.calibration.to_dict()
    bad["K"] = [[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    with pytest.raises(streamcal.CalibrationFileError, match="here.json: key 'K'"):
        streamcal.Calibration.from_dict(bad, source="here.json")


def test_track_html_is_a_small_escaped_table():
    sim = simulate(10.0, seed=2)
    track = streamcal.Track(sim.track.columns, sim.track.metadata, path="a<b>&c.csv")
    text = track._repr_html_()
    assert text.startswith("<table>") and text.endswith("</table>")
    assert "a&lt;b&gt;&amp;c.csv" in text and "a<b>" not in text
    assert f"{len(track)} rows" in text and f"{len(track.mag)} mag" in text
    assert "µT" in text and "m/s²" in text
    duration = track.t[-1] - track.t[0]
    assert f"{duration:.3g} s" in text
    for name in track.columns:
        assert name in text


def test_calibration_html_shows_K_b_effects_rms_n_with_units(fresh):
    sim = simulate(60.0, seed=1, effects={"temperature_offset": 0.3})
    cal = streamcal.fit(sim.track, add="temperature_offset")
    text = cal._repr_html_()
    assert "temperature_offset" in text and "µT/°C" in text and "°C" in text
    assert f"{cal.n} samples" in text and f"{cal.n_outliers} outliers" in text
    assert "K row 1" in text and "b" in text
    assert f"{cal.rms:.4g} µT" in text
    odd = cal.replace(method="<i>x</i>")
    assert "&lt;i&gt;x&lt;/i&gt;" in odd._repr_html_() and "<i>" not in odd._repr_html_()


def test_diagnosis_html_has_verdict_summary_and_the_ladder_with_n(fresh, held):
    for d in (fresh, held):
        text = d._repr_html_()
        assert d.verdict in text and "ladder" in text
        for step in d.ladder:
            assert f"<td>{step['n']}</td>" in text
    text = held._repr_html_()
    assert "bench.json" in text and ", ".join(held.held.parameters) in text
    odd = fresh.replace(summary="a <b> & c")
    text = odd._repr_html_()
    assert "a &lt;b&gt; &amp; c" in text and "<b>" not in text
    assert fresh.summary and fresh.summary.split(":")[0] in fresh._repr_html_()


def test_dir_and_help_list_every_public_name():
    assert dir(streamcal) == sorted(streamcal.__all__)
    assert "Diagnosis" in streamcal.__all__
    from streamcal.diagnosis import Diagnosis

    assert streamcal.Diagnosis is Diagnosis
    text = pydoc.render_doc(streamcal, renderer=pydoc.plaintext)
    for name in streamcal.__all__:
        assert getattr(streamcal, name) is not None
        assert f"``{name}" in streamcal.__doc__, f"the module docstring does not list {name}"
        assert name in text


def test_same_compares_arrays_element_wise_and_nan_as_equal():
    assert same(np.array([1.0, np.nan]), [1.0, float("nan")])
    assert not same(np.array([1.0, 2.0]), np.array([1.0, 2.0, 3.0]))
    assert same({"a": np.zeros(3, bool)}, {"a": np.zeros(3, bool)})
    assert not same({"a": 1}, {"b": 1})
    assert not same([1, 2], (1, 3))
    assert not same(np.zeros(2), None)
