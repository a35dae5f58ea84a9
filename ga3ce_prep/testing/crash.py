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


def _cmd(data: Path, out: Path, sets: list[str]) -> list[str]:
    cmd = [sys.executable, "-m", "ga3ce_prep.cli", "run", "-p", "synthetic", "-d", str(data), "-o", str(out), "-q"]
    for s in sets:
        cmd += ["--set", s]
    return cmd


def _run(cmd: list[str], fault: str = "", kill_after: float | None = None) -> tuple[int, str]:
    env = {**os.environ, "GA3CE_FAULT": fault, "OMP_NUM_THREADS": "1"}
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
