"""The compiled LM engine (streamcal.fitting.lm_fused) and how ``refine`` picks it."""
from __future__ import annotations

import os

import numpy as np
import pytest

from streamcal.fitting import lm, lm_fused
from streamcal.fitting.kernels import Cauchy, GemanMcClure, Huber
from streamcal.model.build import build_effects

from tests.test_lm_equivalence import problem

if lm_fused._numba() is None and not os.environ.get("CI"):
    pytest.skip("numba is not installed (pip install 'streamcal[fast]'); CI runs these",
                allow_module_level=True)


def _both(structure="full", kernel=Cauchy(0.03), **kw):
    m, K0, b0, x0, _ = problem(structure, seed=5, n=400, eta=0.2)
    a = lm.refine(m, K0, b0, x0, kernel=kernel, structure=structure, engine="numpy", **kw)
    f = lm.refine(m, K0, b0, x0, kernel=kernel, structure=structure, engine="compiled", **kw)
    return a, f


@pytest.mark.parametrize("kw", [{}, {"fit_b": False}, {"beta": 0.5}, {"lam0": 1e-3}, {"max_iter": 2}])
def test_compiled_engine_equals_numpy_engine(kw):
    a, f = _both(kernel=GemanMcClure(0.05), **kw)
    assert a.iterations == f.iterations and a.status == f.status
    np.testing.assert_allclose(f.K, a.K, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(f.b, a.b, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(f.x, a.x, atol=1e-10)
    np.testing.assert_allclose(f.residuals, a.residuals, atol=1e-10)
    np.testing.assert_allclose(f.weights, a.weights, atol=1e-10)
    assert f.cost == pytest.approx(a.cost, rel=1e-10)


def test_compiled_engine_refuses_what_it_does_not_cover():
    m, K0, b0, x0, cov = problem("full")
    with pytest.raises(ValueError, match="cauchy and gm"):
        lm.refine(m, K0, b0, x0, kernel=Huber(0.03), engine="compiled")
    effects = build_effects(["temperature_offset"], cov)
    with pytest.raises(ValueError, match="effect terms"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), effects=effects, covariates=cov, engine="compiled")
    with pytest.raises(ValueError, match="unknown LM engine"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="jit")


def test_the_environment_chooses_the_engine_for_the_whole_process(monkeypatch):
    """auto: numpy unless STREAMCAL_LM_ENGINE=compiled, then compiled wherever it applies (other
    kernels stay on numpy); the same choice on every call, whatever ran before."""
    m, K0, b0, x0, _ = problem("full")
    used = []
    real_numpy, real_fused = lm.NumpyEngine, lm_fused.FusedEngine
    monkeypatch.setattr(lm, "NumpyEngine", lambda *a: used.append("numpy") or real_numpy(*a))
    monkeypatch.setattr(lm_fused, "FusedEngine", lambda *a: used.append("compiled") or real_fused(*a))
    monkeypatch.delenv(lm.ENGINE_ENV, raising=False)
    default = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    monkeypatch.setenv(lm.ENGINE_ENV, "compiled")
    first = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    lm.refine(m, K0, b0, x0, kernel=Huber(0.03))
    again = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    assert used == ["numpy", "compiled", "numpy", "compiled"]
    np.testing.assert_array_equal(again.K, first.K)
    np.testing.assert_allclose(first.K, default.K, rtol=1e-10)
    monkeypatch.setenv(lm.ENGINE_ENV, "fast")
    with pytest.raises(ValueError, match="STREAMCAL_LM_ENGINE='fast'"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))


def test_without_numba_compiled_falls_back_to_numpy_with_one_warning(monkeypatch):
    m, K0, b0, x0, _ = problem("full")
    monkeypatch.setattr(lm_fused, "_COMPILED", None)
    monkeypatch.setattr(lm_fused, "_numba", lambda: None)
    monkeypatch.setattr(lm, "_warned_no_numba", False)
    monkeypatch.setenv(lm.ENGINE_ENV, "compiled")
    with pytest.warns(RuntimeWarning, match="numba is not installed"):
        res = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    ref = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="numpy")
    np.testing.assert_array_equal(res.K, ref.K)
    with pytest.raises(ValueError, match="numba is not installed"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="compiled")


def test_warm_up_compiles_every_loop():
    assert lm_fused.warm_up()
    assert all(f.signatures for f in lm_fused._compiled())
