"""The compiled LM engine (streamcal.fitting.lm_fused) and how ``refine`` picks it."""
from __future__ import annotations

import numpy as np
import pytest

from streamcal.fitting import lm, lm_fused
from streamcal.fitting.kernels import Cauchy, GemanMcClure, Huber
from streamcal.model.build import build_effects

from tests.test_lm_equivalence import problem


def _both(structure="full", kernel=Cauchy(0.03), **kw):
    m, K0, b0, x0, _ = problem(structure, seed=5, n=400, eta=0.2)
    a = lm.refine(m, K0, b0, x0, kernel=kernel, structure=structure, engine="numpy", **kw)
    f = lm.refine(m, K0, b0, x0, kernel=kernel, structure=structure, engine="fused", **kw)
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
        lm.refine(m, K0, b0, x0, kernel=Huber(0.03), engine="fused")
    effects = build_effects(["temperature_offset"], cov)
    with pytest.raises(ValueError, match="effect terms"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), effects=effects, covariates=cov, engine="fused")
    with pytest.raises(ValueError, match="unknown LM engine"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="jit")


def test_auto_is_one_choice_per_environment(monkeypatch):
    """auto: the compiled engine wherever it applies, whatever ran before; STREAMCAL_LM_ENGINE=numpy
    keeps numpy (and numba unimported) for the whole process; other kernels always run numpy."""
    m, K0, b0, x0, _ = problem("full")
    used = []
    real_numpy, real_fused = lm.NumpyEngine, lm_fused.FusedEngine
    monkeypatch.setattr(lm, "NumpyEngine", lambda *a: used.append("numpy") or real_numpy(*a))
    monkeypatch.setattr(lm_fused, "FusedEngine", lambda *a: used.append("fused") or real_fused(*a))
    monkeypatch.delenv(lm.ENGINE_ENV, raising=False)
    first = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    lm.refine(m, K0, b0, x0, kernel=Huber(0.03))
    again = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    monkeypatch.setenv(lm.ENGINE_ENV, "numpy")
    pinned = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    assert used == ["fused", "numpy", "fused", "numpy"]
    np.testing.assert_array_equal(again.K, first.K)
    np.testing.assert_allclose(pinned.K, first.K, rtol=1e-10)
    monkeypatch.setenv(lm.ENGINE_ENV, "fast")
    with pytest.raises(ValueError, match="STREAMCAL_LM_ENGINE='fast'"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))


def test_without_numba_auto_and_the_pipeline_use_numpy(monkeypatch):
    m, K0, b0, x0, _ = problem("full")
    monkeypatch.setattr(lm_fused, "_COMPILED", None)
    monkeypatch.setattr(lm_fused, "_numba", lambda: None)
    monkeypatch.delenv(lm.ENGINE_ENV, raising=False)
    assert lm_fused.why_not(lm._Model(m, "full", True, (), {}), Cauchy(0.03)) == "numba is not installed"
    res = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    ref = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="numpy")
    np.testing.assert_array_equal(res.K, ref.K)
    with pytest.raises(ValueError, match="numba is not installed"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="fused")
