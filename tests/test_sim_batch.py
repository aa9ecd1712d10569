"""``streamcal.batch`` and ``streamcal batch`` on simulated tracks: the tests of
tests/test_batch.py (imported below, so their bodies are the same) with its ``paths`` fixture
replaced by three simulated recordings and the same broken file, so a clone without the real
recordings runs them too."""
from __future__ import annotations

import pytest

from streamcal.sim import simulate

from .test_batch import (  # noqa: F401  (collected here, with the paths fixture below)
    test_batch_diagnose_rows_name_a_verdict_and_a_residual,
    test_batch_with_a_thread_pool_matches_a_serial_run, test_cli_batch_rejects_zero_jobs,
    test_cli_batch_with_jobs_writes_one_row_per_file,
    test_dask_distributed_executor_matches_a_serial_run, test_unknown_task_is_an_input_error)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("batch")
    paths = []
    for seed, effects in ((11, {}), (12, {"temperature_offset": 0.05}), (13, {})):
        path = folder / f"sim_{seed}.csv"
        simulate(30.0, seed, effects=effects).track.write(path)
        paths.append(str(path))
    return paths


@pytest.fixture()
def paths(simulated, tmp_path):
    broken = tmp_path / "broken.csv"
    broken.write_text("t,mx,my,mz\n0.0,1.0,2.0,3.0\n0.01,1.0,oops,3.0\n")
    return simulated[:2] + [str(broken)] + simulated[2:]
