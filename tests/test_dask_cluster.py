"""`ga3ce-prep run --scheduler` on a dask cluster started with the standard CLIs (`dask scheduler`,
two `dask worker`s) on loopback: the store equals a local run's, also when a worker is killed
mid-task (dask retries its task on a restarted or the other worker)."""
import os
import subprocess
import sys

import pytest

from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.testing.cluster import dask_cluster
from ga3ce_prep.testing.stores import assert_same_store
from ga3ce_prep.testing.worlds import SMALL

SETS = [*SMALL, "run.shard_size=3"]


@pytest.fixture(scope="module")
def local_store(synth_world, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "local.zarr"
    run_pipeline("synthetic", synth_world, out, overrides=SETS, progress=False)
    return out


def _cli_run(data, out, scheduler):
    cmd = [sys.executable, "-m", "ga3ce_prep.cli", "run", "-p", "synthetic", "-d", str(data), "-o", str(out), "-q",
           "--scheduler", scheduler]
    for o in SETS:
        cmd += ["--set", o]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, "GA3CE_FAULT": ""})


def test_a_dask_cluster_and_a_killed_worker_give_the_local_store(synth_world, local_store, tmp_path):
    marker = tmp_path / "worker-killed"
    marker.touch()  # disarmed for the first run
    # a worker SIGKILLs itself after computing its 4th frame of a stage, before writing the entry
    env = {"GA3CE_FAULT": "stage.frame:4", "GA3CE_FAULT_ONCE": str(marker)}
    with dask_cluster(tmp_path / "cluster", n_workers=2, worker_env=env) as address:
        p = _cli_run(synth_world, tmp_path / "a.zarr", address)
        assert p.returncode == 0, p.stderr[-3000:]
        assert_same_store(tmp_path / "a.zarr", local_store)

        marker.unlink()  # armed: the first worker to reach its 4th frame dies mid-task
        p = _cli_run(synth_world, tmp_path / "b.zarr", address)
        assert p.returncode == 0, p.stderr[-3000:]
        assert marker.exists()  # a worker was killed
        assert_same_store(tmp_path / "b.zarr", local_store)
    logs = "".join(f.read_text() for f in (tmp_path / "cluster").glob("worker-*.log"))
    assert logs.count("was killed by signal 9") == 1, logs[-3000:]  # by its nanny's account
    assert "Restarting worker" in logs
