"""Training on a GPU: does `--device cuda` train and evaluate, does a checkpoint trained there score
the same on the CPU, and how much faster is an epoch than on this machine's CPU threads?

On a machine with CUDA torch and a store (any `ga3ce-prep run` output):

  python benchmarks/gpu_training.py --store out/synthetic.zarr [--cpu-threads 2,16]

1. the paper's GA3CE and ours, `--epochs` epochs, seed 0, `train --device cuda`; wall seconds;
2. each run's best.pt scored by `eval` on the test split with `--device cuda` and `--device cpu`;
3. the paper's GA3CE for `--timing-epochs` epochs on the GPU and on each of `--cpu-threads` CPU
   thread counts: samples/s of the last epoch (history.csv), and the ratio to the first count.
Every step runs the `ga3ce-prep` commands a user would (`python -m ga3ce_prep.cli`), one at a time.
Writes OUT/gpu_training.json.
"""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import click

CLI = [sys.executable, "-m", "ga3ce_prep.cli"]


def run(cmd: list[str], log: Path) -> float:
    """Run a command with its output in `log`; its wall seconds; raise naming the log if it fails."""
    t = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT).returncode
    if rc:
        raise click.ClickException(f"{' '.join(cmd)} failed (exit {rc}); see {log}")
    return time.perf_counter() - t


def last_epoch_rate(run_dir: Path) -> float:
    """Samples/s of the last epoch in a run's history.csv."""
    with open(run_dir / "history.csv") as f:
        return float(list(csv.DictReader(f))[-1]["samples_per_s"])


@click.command(help=__doc__)
@click.option("--store", required=True, type=click.Path(exists=True, file_okay=False), help="The store to train on.")
@click.option("--out", default="runs/gpu_training", show_default=True, help="Folder of the runs and logs.")
@click.option("--epochs", default=20, show_default=True, help="Epochs of the two full runs (the default recipe).")
@click.option("--timing-epochs", default=2, show_default=True, help="Epochs of each timing run.")
@click.option("--cpu-threads", default="2,16", show_default=True, help="CPU thread counts to time against the GPU.")
def main(store: str, out: str, epochs: int, timing_epochs: int, cpu_threads: str) -> None:
    import torch

    if not torch.cuda.is_available():
        raise click.ClickException("no CUDA device (torch.cuda.is_available() is False): this benchmark needs one; "
                                   "install a CUDA build of torch on a machine with an NVIDIA GPU")
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    machine = {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__, "cuda": torch.version.cuda,
               "cpu_count": os.cpu_count()}
    click.echo(f"machine: {machine}")
    result: dict = {"machine": machine, "store": store, "epochs": epochs, "models": {}, "timing": {}}
    for model in ("ga3ce", "ours"):
        run_dir = root / f"{model}-cuda"
        cmd = CLI + ["train", "--store", store, "--out", str(run_dir), "--model", model, "--device", "cuda",
                     "--epochs", str(epochs), "--seed", "0", "--no-progress", "--force"]
        secs = run(cmd, root / f"{model}-cuda.log")
        mae = {}
        for device in ("cuda", "cpu"):
            js = root / f"eval-{model}-{device}.json"
            run(CLI + ["eval", "--store", store, "--checkpoint", str(run_dir / "best.pt"), "--device", device,
                       "--json", str(js), "--cdf", "none", "--no-scenes"], root / f"eval-{model}-{device}.log")
            mae[device] = json.loads(js.read_text())["methods"]["model"]["mae3d"]
        result["models"][model] = {"train_seconds": secs, "test_mae3d": mae}
        click.echo(f"{model}: trained on cuda in {secs:.1f} s; test 3D MAE {mae['cuda']:.4f} (eval on cuda), "
                   f"{mae['cpu']:.4f} (same checkpoint on the CPU)")
    counts = [int(t) for t in cpu_threads.split(",")]
    for device, threads in [("cuda", None)] + [("cpu", t) for t in counts]:
        name = f"timing-{device}" + (f"{threads}" if threads else "")
        cmd = CLI + ["train", "--store", store, "--out", str(root / name), "--device", device, "--epochs",
                     str(timing_epochs), "--seed", "0", "--no-progress", "--force"]
        secs = run(cmd + (["--threads", str(threads)] if threads else []), root / f"{name}.log")
        result["timing"][name] = {"seconds": secs, "samples_per_s": last_epoch_rate(root / name)}
    base = result["timing"][f"timing-cpu{counts[0]}"]["samples_per_s"]
    click.echo(f"the paper's GA3CE, epoch {timing_epochs} of {timing_epochs}, samples/s (x the first CPU count):")
    for name, t in result["timing"].items():
        click.echo(f"  {name:14s} {t['samples_per_s']:7.1f}  ({t['samples_per_s'] / base:.2f}x)   "
                   f"whole run {t['seconds']:.1f} s")
    (root / "gpu_training.json").write_text(json.dumps(result, indent=2))
    click.echo(f"wrote {root / 'gpu_training.json'}")


if __name__ == "__main__":
    main()
