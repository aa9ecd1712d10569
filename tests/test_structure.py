"""The package's shape: the public API cannot be shadowed, imports point down the layers, no
module imports one that (directly or not) imports it back."""
from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("streamcal", "firmware_bridge")


def _all_modules() -> list[str]:
    names = []
    for package in PACKAGES:
        pkg = importlib.import_module(package)
        names.append(package)
        names += [m.name for m in pkgutil.walk_packages(pkg.__path__, prefix=f"{package}.")]
    return names


def _small_track():
    from streamcal.sim import simulate

    return simulate(40.0, seed=3).track


@pytest.mark.slow
def test_public_api_stays_callable_after_every_module_is_imported():
    for name in _all_modules():
        if name.endswith("__main__"):
            continue
        importlib.import_module(name)
    import streamcal
    from streamcal import diagnose, fit

    track = _small_track()
    for _ in range(2):
        assert callable(streamcal.fit) and callable(streamcal.diagnose)
        assert callable(streamcal.batch)
        cal = streamcal.fit(track)
        assert np.isfinite(cal.rms) and cal.K.shape == (3, 3)
        d = streamcal.diagnose(track, model=cal.model)
        assert d.verdict in ("at_noise_floor", "effect_missing", "unexplained")
    assert fit is streamcal.fit and diagnose is streamcal.diagnose
    from streamcal import batch
    from streamcal.batching import batch as batch_function

    assert batch is streamcal.batch is batch_function


def test_layers_contract_holds():
    # In a subprocess: import-linter configures logging in the process that runs it.
    proc = subprocess.run([sys.executable, "-c", "import sys; from importlinter.cli import "
                           "lint_imports; sys.exit(lint_imports(config_filename=sys.argv[1]))",
                           str(REPO / "pyproject.toml")], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]


def _strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):   # Tarjan; the module graph is small enough for recursion
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_counting_imports_inside_functions():
    grimp = pytest.importorskip("grimp")   # import-linter's own graph builder
    graph = grimp.build_graph(*PACKAGES)
    edges = {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    cycles = _strongly_connected(edges)
    assert cycles == [], f"import cycles: {cycles}"
