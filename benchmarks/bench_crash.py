"""The long crash campaign (`make bench-crash`): kill -9 `ga3ce-prep run` at --kills random moments
(failpoints mid-stage, in cache writes and in finalize, and timers), resuming each time; after
every kill --out holds the older store, nothing, or the finished one, and every completed store
equals an uninterrupted run's bit for bit (ga3ce_prep/testing/crash.py; the suite runs a short one).
Then the faults a run lives through: --worker-kills runs of `run -j 2` with one dask worker
SIGKILLed mid-task, and --stalls runs with --out on moto's S3 server frozen --stall-s seconds at a
random moment; every store compared with an uninterrupted run's, bit for bit. Prints, per kind of
fault, the runs, how many the fault hit, and the stores compared.
World: a 160x120 synthetic GFIE world of 6 scenes x 4 frames, 3 frames per shard (8 shards), generated
once into out/bench/crash-world. Takes the CPU lock (cpu_lock.py) itself (--no-lock: not).

    python benchmarks/bench_crash.py [--kills 60 --worker-kills 10 --stalls 5 --stall-s 20 --seed 0 --no-lock
                                      --json out/bench/bench_crash.json]
"""
from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict
from pathlib import Path

import click

from cpu_lock import cpu_lock

ROOT = Path(__file__).resolve().parent.parent
WORLD = dict(scenes=6, frames_per_scene=4, seed=7, width=160)


@click.command()
@click.option("--kills", default=60, show_default=True, help="Kills in all.")
@click.option("--worker-kills", default=10, show_default=True, help="Runs of -j 2 with a worker killed.")
@click.option("--stalls", default=5, show_default=True, help="Runs on S3 with the endpoint frozen.")
@click.option("--stall-s", default=20.0, show_default=True, help="Seconds the endpoint is frozen.")
@click.option("--seed", default=0, show_default=True, help="Seed of the moments.")
@click.option("--json", "json_out", default=str(ROOT / "out" / "bench" / "bench_crash.json"), show_default=True)
@click.option("--no-lock", is_flag=True, help="Do not take the CPU lock (a correctness check; its seconds are not "
                                              "figures then).")
def main(kills, worker_kills, stalls, stall_s, seed, json_out, no_lock):
    """Crash campaign (module docstring)."""
    from ga3ce_prep.synthetic import generate
    from ga3ce_prep.testing import crash
    from ga3ce_prep.testing.worlds import SMALL

    base = ROOT / "out" / "bench"
    data, stamp = base / "crash-world", base / "crash-world" / ".bench"
    sets = [*SMALL, "run.shard_size=3"]
    with cpu_lock(not no_lock):
        if not stamp.is_file() or stamp.read_text() != repr(WORLD):
            shutil.rmtree(data, ignore_errors=True)
            generate("gfie", data, progress=False, **WORLD)
            stamp.write_text(repr(WORLD))
        t = time.perf_counter()

        def log(m: str) -> None:
            print(f"{time.perf_counter() - t:7.1f} s  {m}", flush=True)

        r = crash.crash_campaign(data, base / "crash", kills=kills, sets=sets, seed=seed, log=log)
        kinds = [crash.FaultReport("kill -9 at random moments, resumed", r.runs, r.kills, r.cycles, r.seconds)]
        if worker_kills:
            kinds.append(crash.worker_kills(data, base / "crash-workers", worker_kills, sets, seed=seed, log=log))
        if stalls:
            kinds.append(crash.store_stalls(data, base / "crash-s3", stalls, sets, stall_s=stall_s, seed=seed,
                                            log=log))
    res = {"kills": r.kills, "runs": r.runs, "cycles": r.cycles, "by_moment": dict(r.by_moment), "seconds": r.seconds,
           "frames_lost": 0, "faults": [asdict(k) for k in kinds], "seed": seed, "world": WORLD}
    Path(json_out).parent.mkdir(parents=True, exist_ok=True)
    Path(json_out).write_text(json.dumps(res, indent=2))
    print(f"\ncrash campaign: {r.kills} kills in {r.runs} runs, {r.cycles} completed stores all bit for bit the same "
          f"as an uninterrupted run's ({r.seconds:.0f} s)")
    print("  kills by moment: " + ", ".join(f"{k} {v}" for k, v in sorted(r.by_moment.items())))
    print(f"\n{'fault':<40} {'runs':>5} {'hit':>5} {'stores compared':>16} {'seconds':>8}")
    for k in kinds:
        print(f"{k.kind:<40} {k.runs:>5} {k.faults:>5} {k.compared:>16} {k.seconds:>8.0f}")
    print("every store compared is an uninterrupted run's, bit for bit")
    print(f"figures: {json_out}")


if __name__ == "__main__":
    main()
