"""Fault injection for the kill-and-resume tests: with GA3CE_FAULT="point:n" set, the process
SIGKILLs itself the n-th time it reaches `point` (inert when the variable is unset).

Points: "stage.frame" (a stage has computed a frame, its entry not yet written), "cache.tmp" (an
entry's bytes written to a temporary file, or about to be PUT, not yet in place), "cache.saved"
(an entry in place), "finalize.shard" (a shard appended to the partial store), "finalize.swap"
(the partial store complete, not yet renamed over --out; remote: every array written, the root
metadata not yet), "finalize.aside" (the previous store moved aside, the new one not yet in
place; remote: the previous store's root metadata removed).

GA3CE_FAULT_ONCE=FILE (optional) makes it one kill across every process that shares FILE (the
workers of a dask cluster, their restarts): a process dies at its n-th hit or later, and only if it
is the first to create FILE. An existing FILE disarms the fault.
"""
from __future__ import annotations

import os
import signal
import threading

_counts: dict[str, int] = {}
_lock = threading.Lock()


def fault(point: str) -> None:
    spec = os.environ.get("GA3CE_FAULT")
    if not spec:
        return
    name, _, n = spec.partition(":")
    if name != point:
        return
    once = os.environ.get("GA3CE_FAULT_ONCE")
    with _lock:
        _counts[point] = _counts.get(point, 0) + 1
        hit = _counts[point] >= int(n or 1) if once else _counts[point] == int(n or 1)
    if hit and once:
        try:
            os.close(os.open(once, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return
    if hit:
        os.kill(os.getpid(), signal.SIGKILL)
