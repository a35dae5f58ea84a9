"""The SHA-256 of a file's bytes, the package's one way to name a file by its contents: the cache
keys of stages that read model files (pipeline/run.py), the provenance of the models a store was
made with, the registry's pinned models (weights/registry.py), and the export commands' output."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

_memo: dict[tuple[str, int, int], str] = {}


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, memoised per path, size and modification time (a model file
    is read once per process however many backends, shards and checks ask)."""
    st = os.stat(path)
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _memo:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _memo[key] = h.hexdigest()
    return _memo[key]
