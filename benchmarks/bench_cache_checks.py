"""The cost of the stage cache's checks on read and write (docs/pipeline.md, "Cache, resume,
partial recomputation"): every `.npz` member's CRC-32 (`zipfile.testzip`) and the SHA-256 of the
entry's arrays (`content_digest`, the member `content_sha256`; computed once at the write and once
at each read), against reading the entry without them (the file's bytes and `np.load`), on the
code's own calls (`pipeline/cache.py::Cache.load`, `content_digest`).

Entries: a depth-map entry of `--frames` 640x480 float32 maps (the size `run.cache_depth_maps`
keeps; 10 frames: 12.3 MB) and a default-sized entry (a shard's view, a few KB). Each time is the
best of `--repeat` in one process, one thread, page cache warm; the files go to a temporary folder.

    python benchmarks/bench_cache_checks.py [--frames 10] [--repeat 20]
"""
from __future__ import annotations

import io
import tempfile
import timeit
import zipfile
from collections.abc import Callable
from pathlib import Path

import click
import numpy as np


def _best(fn: Callable[[], object], repeat: int) -> float:
    """The fastest of `repeat` calls of fn, seconds."""
    return min(timeit.repeat(fn, number=1, repeat=repeat))


def _entry(frames: int, maps: bool) -> dict[str, np.ndarray]:
    """A depth-stage entry with its required arrays (cache.ENTRY_ARRAYS, STAGE_ARRAYS["depth"]),
    plus `frames` depth maps when `maps`."""
    rng = np.random.default_rng(0)
    e = {"ids": np.array([f"frame{i:06d}" for i in range(frames)]), "ok": np.ones(frames, bool),
         "fail_idx": np.zeros(0, np.int64), "fail_error": np.array([], str), "fail_message": np.array([], str),
         "valid_frac": rng.random(frames).astype(np.float32), "filled_frac": rng.random(frames).astype(np.float32)}
    if maps:
        e["depth"] = rng.uniform(0.5, 8.0, (frames, 480, 640)).astype(np.float32)
    return e


@click.command()
@click.option("--frames", default=10, show_default=True, help="Depth maps in the large entry.")
@click.option("--repeat", default=20, show_default=True, help="Best of this many.")
def main(frames: int, repeat: int) -> None:
    import torch

    from ga3ce_prep.pipeline.cache import DIGEST, Cache, content_digest

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        cache = Cache(Path(tmp))
        print(f"{'entry':<28} {'MB':>6} {'read, no checks':>16} {'CRC-32':>8} {'SHA-256':>8} {'Cache.load':>11}"
              f"   (ms, best of {repeat})")
        for name, arrays in (("default (a shard's view)", _entry(32, False)),
                             (f"{frames} depth maps 640x480", _entry(frames, True))):
            p = cache.save("depth", f"{name[:2]}0000", arrays)
            data = Path(p).read_bytes()
            mb = len(data) / 1e6

            def read_plain(path: Path = Path(p)) -> None:
                with np.load(io.BytesIO(path.read_bytes()), allow_pickle=False) as z:
                    {k: z[k] for k in z.files}

            def crc(data: bytes = data) -> None:
                with zipfile.ZipFile(io.BytesIO(data)) as z:
                    assert z.testzip() is None

            entry = {k: v for k, v in cache.load("depth", f"{name[:2]}0000").items() if k != DIGEST}
            t_read = _best(read_plain, repeat)
            t_crc = _best(crc, repeat)
            t_sha = _best(lambda entry=entry: content_digest(entry), repeat)
            t_load = _best(lambda name=name: cache.load("depth", f"{name[:2]}0000"), repeat)
            print(f"{name:<28} {mb:6.2f} {1e3 * t_read:16.2f} {1e3 * t_crc:8.2f} {1e3 * t_sha:8.2f} "
                  f"{1e3 * t_load:11.2f}")
            if mb > 1:
                print(f"  per MB: CRC-32 {1e3 * t_crc / mb:.2f} ms, SHA-256 {1e3 * t_sha / mb:.2f} ms; "
                      f"Cache.load {1e3 * t_load:.0f} ms against {1e3 * t_read:.0f} ms read without checks")


if __name__ == "__main__":
    main()
