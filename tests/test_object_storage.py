"""Stores and the stage cache on object storage (`--out s3://bucket/x.zarr`), against moto's S3
server on loopback: killed while caching, while committing and while replacing an older store,
the same command resumes and the store reads back identically to a local run, bit for bit."""
import io
import json
import os
import signal
import subprocess
import sys
import time
import zipfile

import pytest
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.errors import StoreError
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.pipeline.lock import LEASE_S, RunLock
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.cluster import moto_s3
from ga3ce_prep.testing.stores import assert_same_store, store_digests
from ga3ce_prep.testing.worlds import SMALL

SETS = [*SMALL, "run.shard_size=3"]


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    """The moto server's environment, also set in this process; the bucket `bkt`."""
    import fsspec

    with moto_s3(tmp_path_factory.mktemp("moto")) as env:
        saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        fsspec.filesystem("s3").mkdir("bkt")
        try:
            yield env
        finally:
            for k, v in saved.items():
                os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
            fsspec.filesystem("s3").clear_instance_cache()


@pytest.fixture(scope="module")
def local_store(synth_world, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "local.zarr"
    run_pipeline("synthetic", synth_world, out, overrides=SETS, progress=False)
    return out


def _cli_run(data, out, tmp_path, fault="", extra=()):
    cmd = [sys.executable, "-m", "ga3ce_prep.cli", "run", "-p", "synthetic", "-d", str(data), "-o", out, "-q",
           "--summary-json", str(tmp_path / "summary.json")]
    for o in (*SETS, *extra):
        cmd += ["--set", o]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "GA3CE_FAULT": fault, "OMP_NUM_THREADS": "1"})


def _unfinished(url):
    with pytest.raises(StoreError, match="not a finished ga3ce-prep store"):
        open_store(url)


def test_killed_runs_on_s3_resume_to_the_local_store(s3, synth_world, local_store, tmp_path):
    import fsspec

    fs = fsspec.filesystem("s3")
    url = "s3://bkt/runs/a.zarr"
    p = _cli_run(synth_world, url, tmp_path, "cache.saved:5")  # killed while caching
    assert p.returncode == -signal.SIGKILL, p.stderr[-3000:]
    assert not fs.exists(url)
    entries = fs.find("bkt/runs/a.zarr.work/cache")   # the cache is on S3, every entry whole:
    assert len(entries) >= 5                           # the 5th save kills; another thread's may land first
    for e in entries:
        with zipfile.ZipFile(io.BytesIO(fs.cat_file(e))) as z:
            assert z.testzip() is None, e
    p = _cli_run(synth_world, url, tmp_path, "finalize.swap:1")  # killed with every array written
    assert p.returncode == -signal.SIGKILL, p.stderr[-3000:]
    _unfinished(url)
    p = _cli_run(synth_world, url, tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["store_written"] and sum(summary["computed_shards"].values()) == 0
    assert_same_store(url, local_store)
    assert store_digests(url) == store_digests(local_store)  # bit for bit
    assert not fs.exists("bkt/runs/a.zarr.work/lock")  # the lease is released
    info = CliRunner().invoke(cli, ["info", url])
    assert info.exit_code == 0, info.output

    # an older store at --out, killed once it is uncommitted: the rerun still gives the store
    p = _cli_run(synth_world, url, tmp_path, extra=["stages.view.params.mean_error_deg=30"])
    assert p.returncode == 0, p.stderr[-3000:]
    p = _cli_run(synth_world, url, tmp_path, "finalize.aside:1")
    assert p.returncode == -signal.SIGKILL, p.stderr[-3000:]
    _unfinished(url)
    p = _cli_run(synth_world, url, tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    assert store_digests(url) == store_digests(local_store)


def test_a_remote_store_with_a_local_work_directory(s3, synth_world, local_store, tmp_path):
    s = run_pipeline("synthetic", synth_world, "s3://bkt/b.zarr", overrides=SETS, progress=False,
                     work_dir=tmp_path / "work")
    assert s.store_written and any((tmp_path / "work" / "cache").iterdir())
    assert store_digests("s3://bkt/b.zarr") == store_digests(local_store)


def test_the_lease_refuses_a_live_run_elsewhere_and_takes_over_a_dead_one(s3, tmp_path):
    import fsspec

    fs = fsspec.filesystem("s3")
    work, out = "s3://bkt/leased.work", str(tmp_path / "x")   # out's local lock file: out + ".lock"
    with RunLock(work, out):
        with pytest.raises(StoreError, match="another ga3ce-prep run is writing .*x"):
            RunLock(work, out).__enter__()  # this machine's flock
    assert not fs.exists(f"{work}/lock")

    def lease(**record):
        fs.pipe_file(f"{work}/lock", json.dumps({"host": "elsewhere", "pid": 1, "started": "then", **record}).encode())

    lease(heartbeat=time.time())  # a live run on another machine
    with pytest.raises(StoreError, match=r"pid 1 on elsewhere.*last heard of \d+ s ago"):
        RunLock(work, out).__enter__()
    lease(heartbeat=time.time() - LEASE_S - 1)  # its run died
    with RunLock(work, out):
        assert json.loads(fs.cat_file(f"{work}/lock"))["pid"] == os.getpid()


def test_remote_paths_are_checked_before_any_work(s3, synth_world, tmp_path):
    from ga3ce_prep.errors import ConfigError

    with pytest.raises(ConfigError, match="bucket nobucket does not exist"):
        run_pipeline("synthetic", synth_world, "s3://nobucket/x.zarr", overrides=SETS, progress=False)


def test_a_local_store_with_its_work_directory_on_s3(s3, synth_world, local_store, tmp_path):
    """The cache on object storage, the store built beside --out and renamed over it."""
    import fsspec

    s = run_pipeline("synthetic", synth_world, tmp_path / "x.zarr", overrides=SETS, progress=False,
                     work_dir="s3://bkt/x.work")
    assert s.store_written and fsspec.filesystem("s3").find("bkt/x.work/cache")
    assert store_digests(tmp_path / "x.zarr") == store_digests(local_store)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.zarr", "x.zarr.lock"]  # no scratch left beside it
