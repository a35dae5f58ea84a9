"""The shared-machine convention of the benchmarks: one CPU-heavy job at a time, under a file lock."""
from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

LOCK = Path(tempfile.gettempdir()) / "ga3ce-cpu.lock"   # the CPU lock, in the system's temporary folder
CLI = [sys.executable, "-m", "ga3ce_prep.cli"]   # the ga3ce-prep command of this interpreter


@contextmanager
def cpu_lock(enabled: bool = True) -> Iterator[None]:
    """Hold the CPU lock `LOCK` (exclusive) for the block; say how long we waited for it."""
    if not enabled:
        yield
        return
    with open(LOCK, "a") as f:
        t = time.perf_counter()
        fcntl.flock(f, fcntl.LOCK_EX)
        waited = time.perf_counter() - t
        if waited > 1:
            print(f"(waited {waited:.0f} s for {LOCK})", flush=True)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def run_locked(cmd: list[str], threads: int = 2) -> None:
    """Print and run a command under the lock with `threads` OpenMP/MKL threads; raise if it fails."""
    print("$ " + " ".join(cmd), flush=True)
    with cpu_lock():
        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
        subprocess.run(cmd, check=True, env=env)
