"""The store commands `info`, `show`, `export` (registered in ga3ce_prep/cli.py), and `info`'s text:
what a store holds (splits, scenes, frames, the synthetic world's protocol, object-count
histogram, ground truth present, provenance, failures, integrity record)."""
from __future__ import annotations

import json
import os
from collections import Counter

import click
import numpy as np

from .store import ContextStore, open_store

HIST_EDGES = (0, 1, 5, 10, 20, 40, 80, 160)


def _bar(n: int, peak: int, width: int = 30) -> str:
    return "#" * (int(round(width * n / peak)) if peak else 0)


def describe_store(s: ContextStore, max_failures: int = 8) -> str:
    """`ga3ce-prep info`'s text for an opened store (its integrity line says whether it was verified)."""
    fr, a = s.frames, s.attrs
    n = len(s)
    lines = [f"store        {s.path}",
             f"schema       {a.get('schema_version')}   package {a.get('package_version')}"]
    ds = a.get("dataset", {})
    pl = a.get("pipeline", {})
    lines.append(f"dataset      {ds.get('name')} at {ds.get('root')}")
    world = ds.get("synthetic")
    if world:
        preset = f", preset {world['preset']}" if world.get("preset") else ""
        lines.append(f"synthetic    {world.get('protocol')} ({world.get('rooms')} rooms, seed "
                     f"{world.get('seed')}{preset})")
    lines.append(f"pipeline     {pl.get('name', '')} ({pl.get('file')}, sha256 {str(pl.get('sha256', ''))[:12]})")
    summ = a.get("summary", {})
    total = summ.get("frames_total", summ.get("frames_in_dataset", n))  # 1.0 stores: the old name
    lines.append(f"frames       {n} (of {total} in the dataset; {total - n} dropped)")
    split_counts = Counter(fr["split"].tolist())
    lines.append("splits       "
                 + ", ".join(f"{name} {split_counts.get(k, 0)}" for k, name in enumerate(s.split_names)))
    scene_counts = Counter(fr["scene"].tolist())
    shown = ", ".join(f"{s.scene_names[k]} {c}" for k, c in sorted(scene_counts.items())[:8])
    more = f", ... ({len(scene_counts)} scenes)" if len(scene_counts) > 8 else ""
    lines.append(f"scenes       {len(scene_counts)}: {shown}{more}")
    counts = fr["obj_count"].astype(np.int64)
    m = len(s.objects["xyz"])
    lines.append(f"objects      {m} (per frame: mean {counts.mean() if n else 0:.1f}, median "
                 f"{np.median(counts) if n else 0:.0f}, max {counts.max(initial=0)})")
    edges = [*HIST_EDGES, max(HIST_EDGES[-1] + 1, int(counts.max(initial=0)) + 1)]
    bins = [(lo, hi) for lo, hi in zip(edges[:-1], edges[1:])]
    hist = [int(((counts >= lo) & (counts < hi)).sum()) for lo, hi in bins]
    peak = max(hist, default=0)
    for (lo, hi), c in zip(bins, hist):
        label = f"{lo}" if hi == lo + 1 else f"{lo}-{hi - 1}"
        lines.append(f"  {label:>9} objects  {c:>7}  {_bar(c, peak)}")
    gaze_ok = int(np.isfinite(fr["gaze"]).all(1).sum())
    pose_ok = int(np.isfinite(fr["pose"]).all((1, 2)).sum())
    lines.append(f"ground truth gaze in {gaze_ok}/{n} frames; pose complete in {pose_ok}/{n}")
    for stage, names in s.source_names.items():
        used = Counter(fr[f"{stage}_source"].tolist())
        lines.append(f"{stage + ' source':<12} " + ", ".join(f"{names[k] if 0 <= k < len(names) else k} {c}"
                                                          for k, c in sorted(used.items())))
    lines.append("stages")
    for stage, p in a.get("stages", {}).items():
        params = ", ".join(f"{k}={v}" for k, v in (p.get("params") or {}).items())
        tag = "  [ORACLE: synthetic truth]" if p.get("oracle") else ""
        models = ("; models " + ", ".join(f"{k} {v[:12]}" for k, v in p.get("models", {}).items())
                  if p.get("models") else "")
        lines.append(f"  {stage:<8} {p.get('backend')}{tag}: {params}{models}")
    f = s.failures
    nf = len(f.get("frame_id", []))
    lines.append(f"failures     {nf}")
    if nf:
        table = Counter(zip(f["stage"].tolist(), f["error"].tolist(), f["action"].tolist()))
        for (stage, err, action), c in sorted(table.items()):
            lines.append(f"  {stage:<8} {err:<22} {action:<9} {c}")
        for k in range(min(nf, max_failures)):
            lines.append(f"  - {f['frame_id'][k]} [{f['stage'][k]}] {f['message'][k]}")
        if nf > max_failures:
            lines.append(f"  ... {nf - max_failures} more (read them with open_store(path).failures)")
    files = (a.get("integrity") or {}).get("files") or {}
    size = sum(f[0] for f in files.values()) / 1e6
    lines.append("integrity    no record (a store of schema < 1.3)" if not files else
                 f"integrity    {len(files)} files ({size:.1f} MB): every one matches its SHA-256" if s.verified else
                 f"integrity    {len(files)} files ({size:.1f} MB) recorded; not checked (--no-verify)")
    return "\n".join(lines)


@click.command("info")
@click.argument("store", type=click.Path())
@click.option("--failures", "max_failures", type=int, default=8, show_default=True,
              help="How many failure messages to list.")
@click.option("--json", "as_json", is_flag=True,
              help="Print the root attributes (provenance, summary) as JSON instead.")
@click.option("--verify/--no-verify", default=True, show_default=True,
              help="First check every file against the store's integrity record (SHA-256); a damaged store is an "
                   "error naming each damaged array and chunk. --no-verify reads it unchecked.")
def info(store, max_failures, as_json, verify):
    """Print what a store holds: splits, scenes, frames, object-count histogram, provenance, failures.

    The store is first checked against its integrity record (--no-verify skips that)."""
    s = open_store(store, verify=verify)
    click.echo(json.dumps(s.attrs, indent=2) if as_json else describe_store(s, max_failures))


@click.command("show")
@click.argument("store", type=click.Path())
@click.argument("frame_id")
@click.option("--out", "-o", required=True, type=click.Path(dir_okay=False),
              help="F.png: the image with head box, projected objects, t_object, v and ground-truth gaze "
                   "arrows; F.ply: the 3D context as a point set (Open3D).")
@click.option("--data", type=click.Path(file_okay=False), default=None,
              help="Dataset root, if it moved since the store was made (for the image and depth).")
def show(store, frame_id, out, data):
    """Draw one frame's 3D context as a PNG, or write it as a PLY point set (the store is verified first)."""
    from .viz import show as show_frame

    path = show_frame(open_store(store), frame_id, out, data)
    click.echo(f"wrote {path}")


@click.command("export")
@click.argument("store", type=click.Path())
@click.argument("out", type=click.Path(dir_okay=False))
@click.option("--format", "fmt", type=click.Choice(["hdf5"]), default="hdf5", show_default=True,
              help="Output format (HDF5: the store's groups and arrays, names unchanged).")
def export(store, out, fmt):
    """Export a store's arrays to HDF5 for other trainers (same names, shapes and dtypes; the store is verified
    first)."""
    from .store_hdf5 import export_hdf5

    path = export_hdf5(store, out)
    click.echo(f"wrote {path} ({os.path.getsize(path) / 1e6:.1f} MB)")
