"""The long crash campaign (`make bench-crash`): kill -9 `ga3ce-prep run` at --kills random moments
(failpoints mid-stage, in cache writes and in finalize, and timers), resuming each time; after
every kill --out holds the older store, nothing, or the finished one, and every completed store
equals an uninterrupted run's bit for bit (ga3ce_prep/testing/crash.py; the suite runs a short one).
World: a 160x120 synthetic GFIE world of 6 scenes x 4 frames, 3 frames per shard (8 shards), generated
once into out/bench/crash-world. Takes the CPU lock (cpu_lock.py) itself.

    python benchmarks/bench_crash.py [--kills 60 --seed 0 --json out/bench/bench_crash.json]
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import click

from cpu_lock import cpu_lock

ROOT = Path(__file__).resolve().parent.parent
WORLD = dict(scenes=6, frames_per_scene=4, seed=7, width=160)


@click.command()
@click.option("--kills", default=60, show_default=True, help="Kills in all.")
@click.option("--seed", default=0, show_default=True, help="Seed of the moments.")
@click.option("--json", "json_out", default=str(ROOT / "out" / "bench" / "bench_crash.json"), show_default=True)
def main(kills, seed, json_out):
    """Crash campaign (module docstring)."""
    from ga3ce_prep.synthetic import generate
    from ga3ce_prep.testing.crash import crash_campaign
    from ga3ce_prep.testing.worlds import SMALL

    base = ROOT / "out" / "bench"
    data, stamp = base / "crash-world", base / "crash-world" / ".bench"
    with cpu_lock():
        if not stamp.is_file() or stamp.read_text() != repr(WORLD):
            shutil.rmtree(data, ignore_errors=True)
            generate("gfie", data, progress=False, **WORLD)
            stamp.write_text(repr(WORLD))
        t = time.perf_counter()
        r = crash_campaign(data, base / "crash", kills=kills, sets=[*SMALL, "run.shard_size=3"], seed=seed,
                           log=lambda m: print(f"{time.perf_counter() - t:7.1f} s  {m}", flush=True))
    res = {"kills": r.kills, "runs": r.runs, "cycles": r.cycles, "by_moment": dict(r.by_moment), "seconds": r.seconds,
           "frames_lost": 0, "seed": seed, "world": WORLD}
    Path(json_out).parent.mkdir(parents=True, exist_ok=True)
    Path(json_out).write_text(json.dumps(res, indent=2))
    print(f"\ncrash campaign: {r.kills} kills in {r.runs} runs, {r.cycles} completed stores all bit for bit the same "
          f"as an uninterrupted run's ({r.seconds:.0f} s)")
    print("  kills by moment: " + ", ".join(f"{k} {v}" for k, v in sorted(r.by_moment.items())))
    print(f"figures: {json_out}")


if __name__ == "__main__":
    main()
