"""Fault injection for the kill-and-resume tests: with GA3CE_FAULT="point:n" set, the process
SIGKILLs itself the n-th time it reaches `point` (inert when the variable is unset).

Points: "cache.tmp" (an entry's temp file written, not yet renamed), "cache.saved" (an entry
renamed into place), "finalize.shard" (a shard appended to the partial store), "finalize.swap"
(the partial store complete, not yet renamed over --out), "finalize.aside" (the previous store
moved aside, the new one not yet in place).
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
    with _lock:
        _counts[point] = _counts.get(point, 0) + 1
        hit = _counts[point] == int(n or 1)
    if hit:
        os.kill(os.getpid(), signal.SIGKILL)
