"""An effect is one declaration: a toy effect defined here, registered, is a catalog effect
everywhere at once — ``streamcal.fit(add=…)``, the diagnosis' candidates, the diagnose JSON (the
library's and the command's), the HTML report — and, unregistered, nowhere. The built-in
effects' tables are built from their declarations."""
import json
import re
from pathlib import Path
from typing import Mapping

import numpy as np
import pytest

import streamcal
from streamcal.cli import main
from streamcal.errors import InputError, UnknownEffectError
from streamcal.inputs.track import Track
from streamcal.model import (BY_NAME, CORE_EFFECTS, EFFECT_NAMES, PLAUSIBILITY_BOUNDS,
                             REGISTRATION_EFFECTS, SIMULATED_EFFECTS, TERMS, EffectDeclaration,
                             SimulatorTruth, declarations, register, registered,
                             unregister)
from streamcal.model.linear_term import LinearTerm
from streamcal.report import render_html
from streamcal.sim import simulate
from streamcal.units import effect_params

COLUMN = "coil_drive"          # a made-up auxiliary column, −1 … 1
G_TRUE = np.array([3.0, -2.0, 1.5])   # µT per unit of coil_drive²


class CoilSquare:
    """Toy term: ``f_j = g (q_j − q0)``, ``q = coil_drive²``, ``q0`` its median where built
    (stored), ``g`` (3,) sensor unit per unit of q — the whole LM contract of
    :class:`streamcal.model.effect.Effect`."""

    name = "coil_square"

    def __init__(self, q0: float):
        self.q0 = float(q0)

    @classmethod
    def build(cls, cov):
        return cls(np.nanmedian(np.asarray(cov[COLUMN], float) ** 2))

    @classmethod
    def from_params(cls, params: Mapping):
        if set(params) != {"q0", "g"} or len(params["g"]) != 3:
            raise ValueError(f"{cls.name}: expected parameters q0 and g (3 numbers)")
        return cls(params["q0"])

    def n_params(self):
        return 3

    def initial(self):
        return np.zeros(3)

    def _dq(self, cov):
        return np.asarray(cov[COLUMN], float) ** 2 - self.q0

    def term(self, theta, u, cov):
        return self._dq(cov)[:, None] * np.asarray(theta)[None, :]

    def jac_theta(self, theta, u, cov):
        return self._dq(cov)[:, None, None] * np.eye(3)[None]

    def jac_u(self, theta, u, cov):
        return None

    def to_physical(self, theta, scale):
        return {"q0": self.q0, "g": [float(v) for v in np.asarray(theta) * scale]}

    def from_physical(self, params, scale):
        return np.asarray(params["g"], float) / scale


TOY = EffectDeclaration(
    name="coil_square", meaning="offset growing with the square of the coil drive", n_params="3",
    term=CoilSquare, needs=(COLUMN,), units={"q0": "", "g": "{u}"},
    notes={"g": "per unit of coil drive²"}, bound=0.5, subject="coil drive²")


def _drive(t):
    """Segments of 3 s cycling through −1, 0, 1, 0: the square is uncorrelated with the drive,
    so the linear aux_interference on the same column cannot stand in for the toy."""
    return np.array([-1.0, 0.0, 1.0, 0.0])[(np.asarray(t) // 3.0).astype(int) % 4]


def _with_coil(g):
    """A simulated tumble plus the toy's field ``g (drive² − 0.5)``, driven by the made-up
    column on every row."""
    sim = simulate(60.0, 21).track
    c = sim.columns
    t = c["t"]
    drive = _drive(t)
    mag = np.column_stack([c["mx"], c["my"], c["mz"]])
    mag = mag + (drive ** 2 - 0.5)[:, None] * g   # NaN on the IMU rows stays NaN
    return Track.from_arrays(t, mag=mag, accel=np.column_stack([c["ax"], c["ay"], c["az"]]),
                             gyro=np.column_stack([c["gx"], c["gy"], c["gz"]]), temp=c["temp"],
                             aux={COLUMN: drive}, metadata=sim.metadata)


@pytest.fixture(scope="module")
def track():
    return _with_coil(G_TRUE)


@pytest.fixture(scope="module")
def seen(track, tmp_path_factory):
    """Everything the toy shows up in while registered, then the names after unregistering."""
    out = {}
    with registered(TOY):
        out["names"] = tuple(EFFECT_NAMES)
        out["terms"] = tuple(TERMS)
        out["plain"] = streamcal.fit(track)
        out["cal"] = streamcal.fit(track, add=["coil_square"])
        out["printed"] = str(out["cal"])
        d = streamcal.diagnose(track)
        out["diagnosis"] = d
        out["json"] = json.loads(json.dumps(d.to_dict()))
        out["html"] = render_html(track, d)
        out["without"] = streamcal.diagnose(_with_coil(0.0 * G_TRUE))
        path = tmp_path_factory.mktemp("toy") / "coil.csv"
        track.write(path)
        out["path"] = path
    out["after"] = tuple(EFFECT_NAMES)
    return out


def test_a_registered_effect_is_in_the_catalog_and_gone_after(seen):
    assert seen["names"][-1] == "coil_square" and seen["names"][:-1] == seen["after"]
    assert "coil_square" in seen["terms"]
    assert "coil_square" not in EFFECT_NAMES and "coil_square" not in TERMS


def test_fit_with_the_toy_finds_its_field(seen):
    cal, plain = seen["cal"], seen["plain"]
    g = np.asarray(cal.effects["coil_square"]["g"])
    assert np.linalg.norm(g - G_TRUE) < 0.05 * np.linalg.norm(G_TRUE), g
    assert cal.rms < 0.5 * plain.rms, (cal.rms, plain.rms)
    # its declared unit and the sensor unit: "g [3, -2, 1.5] µT"
    assert "coil_square: q0" in seen["printed"] and "] µT" in seen["printed"].split("coil_square")[1]


def test_diagnose_names_the_toy_with_its_evidence(seen):
    d = seen["diagnosis"]
    top = d.candidates[0]
    assert top.effect == "coil_square" and top.significant
    assert top.evidence.startswith("residual follows coil drive² (r=")
    assert float(top.evidence.split("r=")[1].rstrip(")")) > 0.5
    assert d.verdict == "effect_missing"
    names = [c.effect for c in d.candidates]
    assert "aux_interference" in names   # the same column as an ordinary aux channel
    assert d.candidates[names.index("aux_interference")].rms_after > 1.5 * top.rms_after


def test_a_track_without_the_toys_field_does_not_call_it_missing(seen):
    d = seen["without"]
    toy = [c for c in d.candidates if c.effect == "coil_square"]
    assert toy and not toy[0].significant            # tried, and not called missing
    assert d.verdict == "at_noise_floor"


def test_the_diagnose_json_carries_the_toy(seen):
    j = seen["json"]
    assert j["candidates"][0]["effect"] == "coil_square"
    assert j["candidates"][0]["evidence"] == seen["diagnosis"].candidates[0].evidence
    assert j["ladder"][1]["added"] == "coil_square"
    assert "--add" in j["next_step"] and "coil_square" in j["next_step"]


def test_the_report_shows_the_toy(seen):
    page = seen["html"]
    assert "residual follows coil drive² (r=" in page          # the candidate table
    # the parameter table of the calibration with it added: declared unit and note
    assert "<td>coil_square: g</td>" in page and "µT (per unit of coil drive²)" in page
    assert "misses coil_square" in seen["diagnosis"].summary   # the lead sentences


def test_the_command_line_diagnoses_with_a_registered_effect(seen, capsys):
    with registered(TOY):
        code = main(["diagnose", str(seen["path"]), "--json"])
    assert code == 0
    j = json.loads(capsys.readouterr().out)
    assert j["candidates"][0]["effect"] == "coil_square"
    with pytest.raises(UnknownEffectError):
        streamcal.fit(Track.read(seen["path"]), add=["coil_square"])


def test_register_refuses_what_it_cannot_serve():
    with pytest.raises(ValueError, match="already declared"):
        register(EffectDeclaration(name="temperature_offset", meaning="x", n_params="3",
                                   term=TERMS["temperature_offset"]))
    with pytest.raises(ValueError, match="only term effects"):
        register(EffectDeclaration(name="my_core", meaning="x", n_params="3", kind="core"))
    with pytest.raises(ValueError, match="term class"):
        register(EffectDeclaration(name="no_term", meaning="x", n_params="3"))
    with pytest.raises(ValueError, match="built in"):
        unregister("hard_iron")
    with pytest.raises(UnknownEffectError):
        unregister("never_registered")
    with pytest.raises(RuntimeError), registered(TOY):
        raise RuntimeError("the block fails")
    assert "coil_square" not in EFFECT_NAMES


def test_the_builtin_tables_are_the_declarations():
    decl = declarations()
    assert tuple(EFFECT_NAMES) == tuple(d.name for d in decl)
    assert tuple(CORE_EFFECTS) == tuple(d.name for d in decl if d.kind == "core")
    assert tuple(REGISTRATION_EFFECTS) == tuple(d.name for d in decl if d.kind == "registration")
    assert dict(TERMS) == {d.name: d.term for d in decl if d.kind == "term"}
    assert dict(PLAUSIBILITY_BOUNDS) == {d.name: d.bound for d in decl if d.kind == "term"}
    # the simulator injects every effect but the core ones (K and b are always simulated)
    assert set(SIMULATED_EFFECTS) == set(EFFECT_NAMES) - set(CORE_EFFECTS)


@pytest.mark.parametrize("name", [n for n in EFFECT_NAMES if n not in CORE_EFFECTS])
def test_every_simulated_parameter_has_a_declared_unit(name):
    """The truth the simulator writes has the keys a calibration file has; each key has a unit
    (or is dimensionless by declaration), so no parameter prints as a bare number by accident."""
    kw = {"motor": True} if "aux" in BY_NAME[name].needs else {}
    truth = simulate(3.0, 0, effects={name: 0.01}, **kw).truth.effects[name]
    keys = set(truth) if "channels" not in truth else {
        k for ch in truth["channels"].values() for k in ch}
    assert keys <= set(BY_NAME[name].units), (name, keys, BY_NAME[name].units)
    assert effect_params(name, truth)   # formats without error


DOCS = Path(__file__).resolve().parent.parent / "docs"


def test_the_catalog_table_in_effects_md_is_the_declarations():
    rows = re.findall(r"^\| \[`(\w+)`\]\(#\w+\) \| ([^|]+) \| ([^|]+) \|",
                      (DOCS / "effects.md").read_text(encoding="utf-8"), re.M)
    assert [(n, m.strip(), p.strip()) for n, m, p in rows] == \
        [(d.name, d.meaning, d.n_params) for d in declarations()]


def test_the_bounds_table_of_the_docs_is_the_declared_bounds():
    text = (DOCS / "diagnose_against_calibration.md").read_text(encoding="utf-8")
    rows = dict(re.findall(r"^\s*\| `(\w+)` \| ([0-9.]+) r \|", text, re.M))
    assert {n: float(b) for n, b in rows.items()} == dict(PLAUSIBILITY_BOUNDS)


class WarmOffset(LinearTerm):
    """Toy: an offset linear in temperature under another name, simulated through its term."""

    name = "warm_offset"
    COLUMN, REF, PARAM = "temp", "T1", "w"


WARM = EffectDeclaration(
    name="warm_offset", meaning="toy offset linear in temperature", n_params="3", term=WarmOffset,
    needs=("temp",), units={"T1": "°C", "w": "{u}/°C"},
    simulated=SimulatorTruth("vector", lambda v, env: {"T1": 20.0, "w": v.tolist()}))


def test_a_registered_effect_without_a_field_is_simulated_through_its_term():
    with registered(WARM):
        sim = simulate(20.0, 4, effects={"warm_offset": 0.2}, temp_profile="ramp",
                       temp_delta_c=10.0)
        assert "warm_offset" in SIMULATED_EFFECTS
    truth = sim.truth
    w = np.asarray(truth.effects["warm_offset"]["w"])
    assert truth.effects["warm_offset"]["T1"] == 20.0 and np.isclose(np.linalg.norm(w), 0.2)
    added = truth.mag_clean - truth.directions @ truth.K.T - truth.b
    np.testing.assert_allclose(added, (truth.temp - 20.0)[:, None] * w, atol=1e-9)
    assert np.ptp(truth.temp) > 5.0   # the term varies: the check above is not of zeros
    with pytest.raises(UnknownEffectError):
        simulate(5.0, 4, effects={"warm_offset": 0.2})


def test_simulate_refuses_a_registered_effect_without_simulator_truth():
    with registered(TOY), pytest.raises(InputError, match="no simulator truth"):
        simulate(5.0, 0, effects={"coil_square": 1.0})
