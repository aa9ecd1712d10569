"""The compiled LM engine (streamcal.fitting.lm_compiled, the C loops of _lmcore) and how
``refine`` picks it."""
from __future__ import annotations

import hashlib
import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from streamcal.fitting import lm, lm_blocks, lm_compiled
from streamcal.fitting.kernels import Cauchy, GemanMcClure, Huber
from streamcal.model.build import build_effects

from tests.test_lm_equivalence import problem

if not lm_compiled.available() and not os.environ.get("CI"):
    pytest.skip(f"{lm_compiled.build_status()}; CI builds it", allow_module_level=True)


def test_the_extension_is_built_in_ci():
    """CI installs a C compiler: a build that failed there must not pass as a numpy run."""
    assert lm_compiled.available()


def _both(structure="full", kernel=Cauchy(0.03), **kw):
    m, K0, b0, x0, _ = problem(structure, seed=5, n=400, eta=0.2)
    a = lm.refine(m, K0, b0, x0, kernel=kernel, structure=structure, engine="numpy", **kw)
    f = lm.refine(m, K0, b0, x0, kernel=kernel, structure=structure, engine="compiled", **kw)
    return a, f


@pytest.mark.parametrize("kernel", (Cauchy(0.03), GemanMcClure(0.05)))
@pytest.mark.parametrize("structure", ("full", "diag", "sphere"))
@pytest.mark.parametrize("kw", [{}, {"fit_b": False}, {"lam0": 1e-3}, {"max_iter": 2}])
def test_compiled_engine_equals_numpy_engine(structure, kw, kernel):
    a, f = _both(structure, kernel=kernel, **kw)
    assert a.iterations == f.iterations and a.status == f.status
    np.testing.assert_allclose(f.K, a.K, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(f.b, a.b, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(f.x, a.x, atol=1e-10)
    np.testing.assert_allclose(f.residuals, a.residuals, atol=1e-10)
    np.testing.assert_allclose(f.weights, a.weights, atol=1e-10)
    assert f.cost == pytest.approx(a.cost, rel=1e-10)


def _one_iteration_agrees(m, K0, b0, x0, kernel, lams=(1e-3, 10.0)):
    """cost, the damped Schur system for each λ, the retracted step and the final residuals of
    the compiled engine against the numpy blocks, term by term."""
    model = lm._Model(m, "full", True, (), {})
    m_t, x = np.ascontiguousarray(m.T), np.ascontiguousarray(x0.T)
    ref, got = lm_blocks.NumpyEngine(model, m_t, kernel), lm_compiled.CompiledEngine(model, m_t, kernel)
    f_ref, state = ref.cost(K0, b0, [], x)
    f_got, _ = got.cost(K0, b0, [], x)
    assert np.isfinite(f_got) and f_got == pytest.approx(f_ref, rel=1e-13, abs=1e-28)  # r ~ 1e-17 at n = 1
    ref.linearize(K0, b0, [], x, state)
    got.linearize(K0, b0, [], x, None)
    for lam in lams:
        S_ref, rhs_ref = ref.reduce(lam)
        S_got, rhs_got = got.reduce(lam)
        assert np.isfinite(S_got).all() and np.isfinite(rhs_got).all()
        np.testing.assert_allclose(S_got, S_ref, rtol=1e-12, atol=1e-12 * np.abs(S_ref).max())
        # at n = 1 the only residual is the rounding of a unit-field point (~1e-17): so is rhs
        np.testing.assert_allclose(rhs_got, rhs_ref, rtol=1e-12,
                                   atol=max(1e-12 * np.abs(rhs_ref).max(), 1e-15))
        dp = ref.solve(S_ref, rhs_ref)
        np.testing.assert_allclose(got.step(x, dp), ref.step(x, dp), atol=1e-13)
    for a, b in zip(got.final(K0, b0, [], x, None), ref.final(K0, b0, [], x, state)):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("kernel", (Cauchy(0.03), GemanMcClure(0.05)))
def test_one_iteration_matches_the_numpy_blocks(kernel):
    """A sample exactly at its model point exercises the s ≤ floor branch of the Triggs weights."""
    m, K0, b0, x0, _ = problem("full", seed=3, n=300, eta=0.2)
    m = m.copy()
    m[0] = K0 @ x0[0] + b0
    _one_iteration_agrees(m, K0, b0, x0, kernel)


def test_the_loops_refuse_arrays_of_the_wrong_shape_or_type():
    from streamcal.fitting import _lmcore

    m = np.zeros((3, 4))
    K, b = np.eye(3), np.zeros(3)
    with pytest.raises(ValueError, match=re.escape("x must have shape (3, 4), got (3, 3)")):
        _lmcore.cost(m, np.zeros((3, 3)), K, b, 4, 0, 1.0)
    with pytest.raises(ValueError, match=re.escape("m must have shape (3, 4), got (4, 3)")):
        _lmcore.cost(np.zeros((4, 3)), m, K, b, 4, 0, 1.0)        # samples as rows, not columns
    with pytest.raises(ValueError, match=re.escape("b must have shape (3,), got (1, 3)")):
        _lmcore.cost(m, m, K, b[None], 4, 0, 1.0)
    with pytest.raises(TypeError, match="K must hold float64"):
        _lmcore.cost(m, m, np.eye(3, dtype=np.float32), b, 4, 0, 1.0)
    with pytest.raises(ValueError, match="not C-contiguous"):
        _lmcore.cost(m, np.zeros((4, 3)).T, K, b, 4, 0, 1.0)
    with pytest.raises(ValueError, match=re.escape("work must have shape (14, 4), got (13, 4)")):
        _lmcore.reduce(m, m, K, b, 4, 0, 1.0, 1.0, np.zeros((13, 4)), np.zeros(72))
    with pytest.raises(ValueError, match=re.escape("r must have shape (4, 3), got (3, 4)")):
        _lmcore.residuals(m, m, K, b, 4, 0, 1.0, np.zeros((3, 4)), np.zeros(4), np.zeros(4))
    read_only = np.zeros((3, 4))
    read_only.setflags(write=False)
    with pytest.raises(ValueError, match="read-only"):              # out must be writable
        _lmcore.step(m, 4, np.zeros((14, 4)), np.zeros(12), read_only)


@pytest.mark.parametrize("n", (-1, 2**62))
def test_the_loops_refuse_a_sample_count_that_is_not_one(n):
    from streamcal.fitting import _lmcore

    m = np.zeros((3, 4))
    with pytest.raises(ValueError, match=f"n must be a sample count, got {n}"):
        _lmcore.cost(m, m, np.eye(3), np.zeros(3), n, 0, 1.0)
    with pytest.raises(ValueError, match=f"n must be a sample count, got {n}"):
        _lmcore.step(m, n, np.zeros((14, 4)), np.zeros(12), m.copy())


def test_the_loops_refuse_an_unknown_kernel_id():
    from streamcal.fitting import _lmcore

    m = np.zeros((3, 4))
    with pytest.raises(ValueError, match="kernel_id must be 0 .Cauchy. or 1 .Geman-McClure., got 2"):
        _lmcore.cost(m, m, np.eye(3), np.zeros(3), 4, 2, 1.0)


def test_the_compiled_constants_are_the_python_ones():
    """The floor on s, the clamp on D, the scratch rows and the kernel ids are compiled into the
    loops; a change on either side alone would silently change the fit."""
    from streamcal.fitting import _lmcore, kernels

    assert _lmcore.S_FLOOR == kernels._S_FLOOR
    assert _lmcore.D_MIN == kernels.D_MIN
    assert _lmcore.WORK == lm_compiled._WORK
    assert (_lmcore.KERNEL_CAUCHY, _lmcore.KERNEL_GM) == (lm_compiled._KERNEL_IDS[Cauchy],
                                                          lm_compiled._KERNEL_IDS[GemanMcClure])


@pytest.mark.parametrize("kernel", (Cauchy(0.03), GemanMcClure(0.05)))
@pytest.mark.parametrize("n", (1, 2, 3, 301))
def test_odd_and_tiny_sample_counts_match_the_numpy_blocks(kernel, n):
    """The loops take samples in pairs: the last lone sample of an odd n must count once, also
    when it sits exactly at its model point (s = 0, where ρ″/ρ′ terms are 0·∞ if not masked)."""
    m, K0, b0, x0, _ = problem("full", seed=4, n=max(n, 3), eta=0.0)
    m, x0 = m[:n].copy(), x0[:n].copy()
    m[n - 1] = K0 @ x0[n - 1] + b0
    if n > 2:
        m[1] = K0 @ x0[1] + b0
    _one_iteration_agrees(m, K0, b0, x0, kernel, lams=(1e-3,))


def test_compiled_engine_refuses_what_it_does_not_cover():
    m, K0, b0, x0, cov = problem("full")
    with pytest.raises(ValueError, match="cauchy and gm"):
        lm.refine(m, K0, b0, x0, kernel=Huber(0.03), engine="compiled")
    effects = build_effects(["temperature_offset"], cov)
    with pytest.raises(ValueError, match="effect terms"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), effects=effects, covariates=cov, engine="compiled")
    with pytest.raises(ValueError, match="unknown LM engine"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="jit")


def _engines_used(monkeypatch) -> list:
    """The engines refine builds from now on, in order ('numpy' / 'compiled')."""
    used = []
    real_numpy, real_compiled = lm.NumpyEngine, lm_compiled.CompiledEngine
    monkeypatch.setattr(lm, "NumpyEngine", lambda *a: used.append("numpy") or real_numpy(*a))
    monkeypatch.setattr(lm_compiled, "CompiledEngine",
                        lambda *a: used.append("compiled") or real_compiled(*a))
    return used


def test_the_environment_chooses_the_engine_for_the_whole_process(monkeypatch):
    """unset: compiled wherever it applies (other kernels on numpy); numpy: numpy everywhere;
    the same choice on every call, whatever ran before."""
    m, K0, b0, x0, _ = problem("full")
    used = _engines_used(monkeypatch)
    monkeypatch.delenv(lm.ENGINE_ENV, raising=False)
    first = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    lm.refine(m, K0, b0, x0, kernel=Huber(0.03))
    again = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    monkeypatch.setenv(lm.ENGINE_ENV, "numpy")
    forced = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    monkeypatch.setenv(lm.ENGINE_ENV, "compiled")
    lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    assert used == ["compiled", "numpy", "compiled", "numpy", "compiled"]
    np.testing.assert_array_equal(again.K, first.K)
    np.testing.assert_allclose(forced.K, first.K, rtol=1e-10)
    monkeypatch.setenv(lm.ENGINE_ENV, "fast")
    with pytest.raises(ValueError, match="STREAMCAL_LM_ENGINE='fast'"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))


def test_without_the_extension_numpy_runs_and_compiled_warns_once(monkeypatch):
    m, K0, b0, x0, _ = problem("full")
    monkeypatch.setattr(lm_compiled, "BUILT", False)
    monkeypatch.setattr(lm, "_warned_not_built", False)
    monkeypatch.delenv(lm.ENGINE_ENV, raising=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                              # the default: no warning
        quiet = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    ref = lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="numpy")
    np.testing.assert_array_equal(quiet.K, ref.K)
    monkeypatch.setenv(lm.ENGINE_ENV, "compiled")
    with pytest.warns(RuntimeWarning, match="was not built"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    with pytest.raises(ValueError, match="was not built"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="compiled")


def test_an_explicit_engine_overrides_the_environment_and_the_value_is_forgiving(monkeypatch):
    """engine= on the call wins over the environment; the variable's case and blanks do not
    matter; STREAMCAL_LM_ENGINE=compiled with a kernel the loops do not cover runs numpy
    without a warning (the extension is there, it just does not apply)."""
    m, K0, b0, x0, _ = problem("full")
    used = _engines_used(monkeypatch)
    monkeypatch.setenv(lm.ENGINE_ENV, " Compiled ")
    lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="numpy")
    lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lm.refine(m, K0, b0, x0, kernel=Huber(0.03))
    monkeypatch.setenv(lm.ENGINE_ENV, "NUMPY")
    lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03), engine="compiled")
    lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    monkeypatch.setenv(lm.ENGINE_ENV, "auto")
    lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))
    assert used == ["numpy", "compiled", "numpy", "compiled", "numpy", "compiled"]
    monkeypatch.setenv(lm.ENGINE_ENV, "fast")
    with pytest.raises(ValueError, match="choose auto, numpy or compiled"):
        lm.refine(m, K0, b0, x0, kernel=Cauchy(0.03))


def test_a_build_older_than_its_source_is_told_apart(monkeypatch):
    """setup.py compiles the source's SHA-256 in: an extension built before _lmcore.c was edited
    must not pass for the edited loops (the tests above would then test the old ones)."""
    from streamcal.fitting import _lmcore

    src = Path(lm_compiled.__file__).with_name("_lmcore.c")
    if not src.is_file():
        pytest.skip("an installed package without its C source: nothing to compare")
    assert _lmcore.SOURCE_SHA256 == hashlib.sha256(src.read_bytes()).hexdigest()
    assert not lm_compiled._stale()
    monkeypatch.setattr(lm_compiled, "_BUILT_FROM", "0" * 64)
    assert lm_compiled._stale()
