"""Training throughput and memory on CPU, and the data path alone (`make bench-train`).

Measures, on a toy store with 10-60 objects per frame (ga3ce_prep/testing/toy_store.py):
  - training samples/s of the trainer's own step (forward, arccos loss, backward, clip, AdamW) at
    the paper's sizes, batch 32, with objects padded to a fixed 168 (the paper's GFIE padding),
    padded per batch (random batches), the same batches run as 4 micro-batches of similar count
    (`--micro-batches 4`, the trainer's default: the same step), and padded per batch with batches
    grouped by object count ("mixed": 4 count groups; "sorted": by count, a room or two a batch), with the mean
    number of scenes in a batch;
    each in a fresh subprocess, reporting its peak resident memory (and the increase over the
    process's memory before the first step);
  - the data path alone: ContextDataset.batch (the trainer's vectorised gather) and the generic
    per-frame __getitem__ + collate, in frames/s.
Takes the CPU lock (cpu_lock.py) itself (one heavy job at a time on the shared machine): run it directly,
not under `flock`. Figures are provisional on a busy machine.

    python benchmarks/bench_train.py [--steps 30 --threads 2 --json out.json]
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import click
import numpy as np

from cpu_lock import cpu_lock

ROOT = Path(__file__).resolve().parent.parent
MODES = {"fixed168": dict(n_max=168, batching="shuffled"), "per_batch": dict(n_max=None, batching="shuffled"),
         "per_batch_micro4": dict(n_max=None, batching="shuffled", parts=4),
         "mixed": dict(n_max=None, batching="mixed"), "sorted": dict(n_max=None, batching="sorted")}


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _store(path: Path, frames: int) -> Path:
    from ga3ce_prep.testing.toy_store import write_toy_store

    if not (path / "zarr.json").exists():  # a real store (a synthetic world's) is used as it is
        write_toy_store(path, frames, seed=0)
    return path


def one_mode(store: str, mode: str, steps: int, warmup: int, threads: int, batch: int) -> dict:
    """Train `steps` steps in this process and report samples/s and memory."""
    import torch

    from ga3ce_prep.model import GA3CE
    from ga3ce_prep.train import BucketBatchSampler, ContextDataset
    from ga3ce_prep.train.trainer import setup_torch, train_step

    setup_torch(threads, "cpu")
    ds = ContextDataset(store, "train")
    opts = MODES[mode]
    torch.manual_seed(0)
    model = GA3CE().train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, weight_decay=0.1)
    batches = BucketBatchSampler(ds.obj_count, batch, seed=0, batching=opts["batching"]).batches()
    rooms = float(np.mean([len(np.unique(ds.scene[b])) for b in batches]))
    rss0 = _rss_mb()
    slots = 0.0
    parts = opts.get("parts", 1)
    for i in range(warmup):
        b = ds.batch(batches[i], opts["n_max"])
        train_step(model, opt, b, b.view, 1e-4, 0.1, parts=parts)
    t0 = time.perf_counter()
    n = 0
    for i in range(warmup, warmup + steps):
        b = ds.batch(batches[i % len(batches)], opts["n_max"])
        train_step(model, opt, b, b.view, 1e-4, 0.1, parts=parts)
        n += len(b)
    dt = time.perf_counter() - t0
    for i in range(warmup, warmup + steps):   # padded slots per frame, over the parts (untimed)
        b = ds.batch(batches[i % len(batches)], opts["n_max"])
        slots += (b.mask.shape[1] if parts == 1 else
                  sum(len(p) * p.mask.shape[1] for p, _ in b.split_by_count(parts)) / len(b))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"mode": mode, "samples_per_s": n / dt, "steps": steps, "batch": batch, "threads": threads,
            "mean_object_slots": slots / steps, "scenes_per_batch": rooms, "peak_rss_mb": peak, "rss_before_mb": rss0,
            "peak_increase_mb": peak - rss0}


def data_path(store: str, batch: int, seconds: float = 2.0) -> dict:
    """Frames/s of the data path alone (no model)."""
    import functools

    from ga3ce_prep.train import BucketBatchSampler, ContextDataset, collate

    ds = ContextDataset(store, "train")
    out = {}
    for name, fn in [
        ("batch_per_batch_padding", lambda idx: ds.batch(idx)),
        ("batch_fixed168", lambda idx: ds.batch(idx, 168)),
        ("getitem_collate", lambda idx: functools.partial(collate, n_max=None)([ds[i] for i in idx])),
    ]:
        sampler = BucketBatchSampler(ds.obj_count, batch, seed=1)
        n, t0, epoch = 0, time.perf_counter(), 0
        while time.perf_counter() - t0 < seconds:
            sampler.set_epoch(epoch)
            for idx in sampler.batches():
                fn(idx)
                n += len(idx)
                if time.perf_counter() - t0 >= seconds:
                    break
            epoch += 1
        out[name] = n / (time.perf_counter() - t0)
    out["frames"] = len(ds)
    return out


@click.command()
@click.option("--steps", default=30, show_default=True, help="Timed optimiser steps per mode.")
@click.option("--warmup", default=3, show_default=True, help="Untimed steps first.")
@click.option("--batch", default=32, show_default=True, help="Batch size (paper: 32).")
@click.option("--threads", default=2, show_default=True, help="torch threads.")
@click.option("--frames", default=4000, show_default=True, help="Frames of the toy store.")
@click.option("--store", default=str(ROOT / "out" / "bench_train_toy.zarr"), show_default=True,
              help="Store to train on: a toy store is made there if missing; a real store (make demo's "
                   "out/synthetic.zarr) shows how batches group its scenes.")
@click.option("--json", "json_path", default=None, help="Also write the figures as JSON.")
@click.option("--no-lock", is_flag=True, help="Do not take the CPU lock (benchmarks/cpu_lock.py).")
@click.option("--one", default=None, hidden=True)
def main(steps, warmup, batch, threads, frames, store, json_path, no_lock, one):
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    if one:  # child process: one training mode
        print(json.dumps(one_mode(store, one, steps, warmup, threads, batch)))
        return
    store = str(_store(Path(store), frames))
    results = {"training": [], "conditions": {"threads": threads, "batch": batch, "steps": steps,
                                              "cpus": os.cpu_count(), "load_avg_before": os.getloadavg()}}
    with cpu_lock(not no_lock):
        for mode in MODES:
            cmd = [sys.executable, __file__, "--one", mode, "--store", store, "--steps", str(steps),
                   "--warmup", str(warmup), "--threads", str(threads), "--batch", str(batch)]
            p = subprocess.run(cmd, check=True, capture_output=True, text=True)
            r = json.loads(p.stdout.strip().splitlines()[-1])
            results["training"].append(r)
            click.echo(f"train {mode:10s}: {r['samples_per_s']:7.1f} samples/s  (mean object slots "
                       f"{r['mean_object_slots']:.0f}, {r['scenes_per_batch']:.1f} scenes a batch, "
                       f"peak RSS {r['peak_rss_mb']:.0f} MB, "
                       f"+{r['peak_increase_mb']:.0f} MB over setup)")
        d = data_path(store, batch)
        results["data_path"] = d
    results["conditions"]["load_avg_after"] = os.getloadavg()
    click.echo(f"data path (frames/s, batch {batch}): ContextDataset.batch per-batch padding "
               f"{d['batch_per_batch_padding']:,.0f}, fixed 168 {d['batch_fixed168']:,.0f}; "
               f"__getitem__ + collate {d['getitem_collate']:,.0f}")
    best = max(r["samples_per_s"] for r in results["training"])
    click.echo(f"data path / fastest training = {d['batch_per_batch_padding'] / best:,.0f}x "
               f"(the data path is {'never' if d['batch_per_batch_padding'] > 50 * best else 'NOT safely'} "
               "the bottleneck)")
    click.echo(f"conditions: {threads} threads, load average before {results['conditions']['load_avg_before'][0]:.2f} "
               "(provisional on a shared machine)")
    if json_path:
        Path(json_path).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
