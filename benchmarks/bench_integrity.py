"""The cost of the store's integrity record (docs/store.md): per store size, the time finalize
spends recording every file's SHA-256 (`store.file_digests`, inside `StoreWriter.close`), the
time every reader's check (`ga3ce-prep info`, `open_store`) adds (`verify_store`; "open s" is
`open_store(verify=False)`, the reading alone), and the record's share of the root zarr.json.
Stores are toy worlds (10-60 objects per frame) written with `StoreWriter`; each time is the best
of `--repeat` (page cache warm).

    python benchmarks/bench_integrity.py [--frames 5000 --frames 50000]
"""
from __future__ import annotations

import functools
import json
import shutil
import tempfile
import time
import timeit
from collections.abc import Callable
from pathlib import Path

import click

from cpu_lock import cpu_lock


def _best(fn: Callable[[], object], repeat: int) -> float:
    """The fastest of `repeat` calls of fn, seconds."""
    return min(timeit.repeat(fn, number=1, repeat=repeat))


@click.command()
@click.option("--frames", "sizes", type=int, multiple=True, default=(5000, 50000), show_default=True)
@click.option("--repeat", type=int, default=3, show_default=True)
def main(sizes: tuple[int, ...], repeat: int) -> None:
    from ga3ce_prep.store import file_digests, open_store, verify_store
    from ga3ce_prep.testing.toy_store import write_toy_store

    print(f"{'frames':>7} {'files':>6} {'store MB':>9} {'write s':>8} {'record s':>9} {'open s':>7} "
          f"{'verify s':>9} {'record KB':>10}")
    with cpu_lock(), tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            path = Path(tmp) / f"toy{n}.zarr"
            t = time.perf_counter()
            write_toy_store(path, n_frames=n)
            write = time.perf_counter() - t
            record = _best(functools.partial(file_digests, path), repeat)
            opened = _best(functools.partial(open_store, path, verify=False), repeat)
            verify = _best(functools.partial(verify_store, path), repeat)
            files = json.loads((path / "zarr.json").read_text())["attributes"]["integrity"]["files"]
            size = sum(f[0] for f in files.values()) / 1e6
            rec_kb = len(json.dumps(files)) / 1e3
            print(f"{n:>7} {len(files):>6} {size:>9.1f} {write:>8.2f} {record:>9.3f} {opened:>7.3f} "
                  f"{verify:>9.3f} {rec_kb:>10.1f}", flush=True)
            shutil.rmtree(path)


if __name__ == "__main__":
    main()
