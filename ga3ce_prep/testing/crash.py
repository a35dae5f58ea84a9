"""The crash campaign: kill -9 `ga3ce-prep run` at many random moments, resume it each time, and
check the store bit for bit (tests/test_crash_campaign.py runs a short one, `make bench-crash` a
long one).

Each cycle starts with an older store at --out (another parameter's) and an empty work directory,
then reruns the same command until it completes. The attempts take the kinds of moment in turn (in
a random order): a failpoint (pipeline/faults.py: mid-stage, in a cache write, in finalize) at a
random hit, or a timer at a random moment of an uninterrupted run's wall time; an attempt that
completes first ends the cycle. After every kill --out must hold the older
store, nothing (killed between moving it aside and the rename), or the finished store; after the
completing run it must be the finished store, bit for bit (every file's SHA-256 equal to an
uninterrupted run's).

Two faults that do not kill the run itself, each run checked the same way (`make bench-crash`):
`worker_kills` (`run -j 2` with one dask worker SIGKILLed mid-task, which its nanny restarts) and
`store_stalls` (`--out` on moto's S3 server, frozen for some seconds at a random moment of the run).
"""
from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ga3ce_prep.stages import STAGES
from ga3ce_prep.testing.stores import store_digests

OLDER = "stages.view.params.mean_error_deg=30"


@dataclass
class CampaignReport:
    kills: int = 0
    runs: int = 0  # attempts, killed or completed
    cycles: int = 0  # completed, each checked bit for bit
    by_moment: Counter = field(default_factory=Counter)  # failpoint name or "timer" -> kills
    seconds: float = 0.0


def _cmd(data: Path, out: Path | str, sets: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "ga3ce_prep.cli", "run", "-p", "synthetic", "-d", str(data), "-o", str(out), "-q"]
    for s in sets:
        cmd += ["--set", s]
    return cmd


@dataclass
class FaultReport:
    """Runs that met one kind of fault and completed: `compared` stores, every one bit for bit a
    clean run's."""
    kind: str
    runs: int = 0
    faults: int = 0  # runs the fault did hit (a worker was killed, the endpoint froze mid-run)
    compared: int = 0
    seconds: float = 0.0


def _run(cmd: list[str], fault: str = "", kill_after: float | None = None,
         env: dict[str, str] | None = None) -> tuple[int, str]:
    env = {**os.environ, "GA3CE_FAULT": fault, "OMP_NUM_THREADS": "1", **(env or {})}
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _, err = p.communicate(timeout=kill_after)
    except subprocess.TimeoutExpired:
        p.send_signal(signal.SIGKILL)
        _, err = p.communicate()
    return p.returncode, err


def crash_campaign(data: Path, base: Path, kills: int, sets: list[str], seed: int = 0,
                   log: Callable[[str], None] = lambda _: None) -> CampaignReport:
    """Kill the run `kills` times (module docstring); raises AssertionError at the first store that
    is not one of the allowed ones, or a resumed run that fails."""
    rng = random.Random(seed)
    base.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ref, older = base / "ref.zarr", base / "older.zarr"
    wall = {}  # an uninterrupted run's wall time: the timer kills' range
    for path, extra in ((ref, []), (older, [OLDER])):
        shutil.rmtree(path, ignore_errors=True)
        shutil.rmtree(f"{path}.work", ignore_errors=True)
        t = time.perf_counter()
        rc, err = _run(_cmd(data, path, [*sets, *extra]))
        assert rc == 0, err[-3000:]
        wall[path] = time.perf_counter() - t
    want, was = store_digests(ref), store_digests(older)
    from ga3ce_prep.store import open_store

    s = open_store(ref)
    shards, frames = s.attrs["run"]["n_shards"], s.attrs["summary"]["frames_total"]
    hits = {"stage.frame": frames * len(STAGES), "cache.tmp": shards * len(STAGES), "cache.saved": shards * len(STAGES),
            "finalize.shard": shards, "finalize.swap": 1, "finalize.aside": 1}
    out = base / "run.zarr"
    cmd = _cmd(data, out, sets)
    report = CampaignReport()

    def new_cycle() -> None:
        shutil.rmtree(out, ignore_errors=True)
        shutil.rmtree(f"{out}.work", ignore_errors=True)
        shutil.copytree(older, out)

    moments: list[str] = []
    new_cycle()
    while True:
        if report.kills < kills:
            if not moments:  # every kind of moment in turn, in a random order
                moments = rng.sample([*sorted(hits), "timer"], len(hits) + 1)
            moment = moments.pop()
            if moment == "timer":
                rc, err = _run(cmd, kill_after=rng.uniform(0.0, wall[ref]))
            else:
                rc, err = _run(cmd, fault=f"{moment}:{rng.randint(1, hits[moment])}")
        else:
            moment, (rc, err) = "none", _run(cmd)
        report.runs += 1
        if rc == -signal.SIGKILL:
            report.kills += 1
            report.by_moment[moment] += 1
            now = store_digests(out) if out.exists() else None
            assert now in (was, want, None), f"after a kill ({moment}) --out holds neither store"
            log(f"kill {report.kills}/{kills}: {moment}")
            continue
        assert rc == 0, f"a resumed run failed (exit {rc}): {err[-3000:]}"
        assert store_digests(out) == want, "the completed store differs from an uninterrupted run's"
        report.cycles += 1
        log(f"cycle {report.cycles} complete after {report.kills} kills: the store is bit for bit the same")
        if report.kills >= kills:
            break
        new_cycle()
    report.seconds = time.perf_counter() - t0
    return report


def _reference(data: Path, base: Path, sets: list[str]) -> tuple[dict[str, str], int, float]:
    """An uninterrupted local run's store digests, its frames and its wall time."""
    from ga3ce_prep.store import open_store

    ref = base / "ref.zarr"
    shutil.rmtree(ref, ignore_errors=True)
    shutil.rmtree(f"{ref}.work", ignore_errors=True)
    t = time.perf_counter()
    rc, err = _run(_cmd(data, ref, sets))
    assert rc == 0, err[-3000:]
    return store_digests(ref), open_store(ref).attrs["summary"]["frames_total"], time.perf_counter() - t


def worker_kills(data: Path, base: Path, runs: int, sets: list[str], seed: int = 0,
                 log: Callable[[str], None] = lambda _: None) -> FaultReport:
    """`run -j 2`, `runs` times from an empty work directory, one worker SIGKILLed in each (its
    `stage.frame` failpoint at a random hit, once across the workers and their restarts); every
    store must be an uninterrupted run's bit for bit."""
    rng = random.Random(seed)
    base.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    want, frames, _ = _reference(data, base, sets)
    out, marker = base / "workers.zarr", base / "worker-killed"
    report = FaultReport("a dask worker killed (-j 2)")
    for _ in range(runs):
        shutil.rmtree(out, ignore_errors=True)
        shutil.rmtree(f"{out}.work", ignore_errors=True)
        marker.unlink(missing_ok=True)
        n = rng.randint(1, max(1, frames * len(STAGES) // 2))
        rc, err = _run([*_cmd(data, out, sets), "-j", "2"], fault=f"stage.frame:{n}",
                       env={"GA3CE_FAULT_ONCE": str(marker)})
        assert rc == 0, f"a run whose worker was killed failed (exit {rc}): {err[-3000:]}"
        report.runs += 1
        report.faults += marker.exists()
        assert store_digests(out) == want, "a store whose worker was killed differs from an uninterrupted run's"
        report.compared += 1
        log(f"worker kill {report.runs}/{runs} (stage.frame:{n}, {'killed' if marker.exists() else 'not reached'}): "
            "the store is bit for bit the same")
    report.seconds = time.perf_counter() - t0
    return report


def store_stalls(data: Path, base: Path, runs: int, sets: list[str], stall_s: float = 20.0, seed: int = 0,
                 log: Callable[[str], None] = lambda _: None) -> FaultReport:
    """`run --out s3://...` against moto's S3 server, `runs` times from an empty work directory,
    the server frozen (SIGSTOP) for `stall_s` seconds at a random moment of an unfrozen run's wall
    time; every store must be a local uninterrupted run's bit for bit."""
    import fsspec

    from ga3ce_prep.testing.cluster import frozen, moto_server

    rng = random.Random(seed)
    base.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    want, _, _ = _reference(data, base, sets)
    report = FaultReport(f"the S3 endpoint frozen {stall_s:g} s")
    with moto_server(base / "moto") as (env, server):
        saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        try:
            fsspec.filesystem("s3").mkdir("bkt")
            t = time.perf_counter()
            rc, err = _run(_cmd(data, "s3://bkt/unfrozen.zarr", sets))  # the moments' range
            assert rc == 0, err[-3000:]
            wall = time.perf_counter() - t
            for i in range(runs):
                url, after = f"s3://bkt/stall{i}.zarr", rng.uniform(0.0, wall)
                t = time.perf_counter()
                freeze = frozen(server, after, stall_s)
                rc, err = _run(_cmd(data, url, sets))
                took = time.perf_counter() - t
                freeze.join()
                assert rc == 0, f"a run whose endpoint froze failed (exit {rc}): {err[-3000:]}"
                report.runs += 1
                report.faults += after < took
                assert store_digests(url) == want, "a store whose endpoint froze differs from an uninterrupted run's"
                report.compared += 1
                log(f"stall {i + 1}/{runs} at {after:.1f} s of a {took:.1f} s run: the store is bit for bit the same")
        finally:
            for k, v in saved.items():
                os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
            fsspec.filesystem("s3").clear_instance_cache()
    report.seconds = time.perf_counter() - t0
    return report
