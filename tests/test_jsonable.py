"""streamcal.calibration.jsonable: every output written as JSON goes through it."""
import json
import math

import numpy as np

from streamcal.calibration import jsonable


def test_numpy_values_become_plain_json_values():
    value = {"n": np.int64(7), "ok": np.bool_(True), "x": np.float32(0.5),
             "v": np.array([1.0, 2.0]), "m": np.arange(4).reshape(2, 2), "s": np.array(3.0),
             "t": (np.int32(1), "a"), 5: None}
    out = jsonable(value)
    assert out == {"n": 7, "ok": True, "x": 0.5, "v": [1.0, 2.0], "m": [[0, 1], [2, 3]],
                   "s": 3.0, "t": [1, "a"], "5": None}
    assert type(out["n"]) is int and type(out["ok"]) is bool and type(out["x"]) is float
    assert type(out["m"][1][0]) is int
    json.dumps(out, allow_nan=False)          # no default= hook needed


def test_non_finite_numbers_are_null():
    value = {"sigma": float("nan"), "rms": np.float64("inf"), "a": np.array([1.0, np.nan]),
             "f": -math.inf}
    assert jsonable(value) == {"sigma": None, "rms": None, "a": [1.0, None], "f": None}
