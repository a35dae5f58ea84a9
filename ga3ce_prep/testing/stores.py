"""Store comparisons for the tests: array for array, and byte for byte."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from ga3ce_prep.store import open_store


def assert_same_store(a: str | Path, b: str | Path, attrs: bool = True) -> None:
    """Every array of stores a and b equal (values and dtypes), the scene names too, and (attrs)
    the root attributes."""
    sa, sb = open_store(a), open_store(b)
    for group in ("frames", "objects", "failures"):
        ga, gb = getattr(sa, group), getattr(sb, group)
        assert sorted(ga) == sorted(gb)
        for name in ga:
            np.testing.assert_array_equal(ga[name], gb[name], err_msg=f"{group}/{name}")
            assert ga[name].dtype == gb[name].dtype
    assert sa.scene_names == sb.scene_names
    if attrs:
        assert sa.attrs == sb.attrs


def store_digests(path: str | Path) -> dict[str, str]:
    """SHA-256 of every file (object) of a store, by its path inside the store: two stores are the
    same bit for bit when these are equal. path: a local directory or an fsspec URL."""
    import fsspec

    fs, root = fsspec.core.url_to_fs(str(path))
    root = root.rstrip("/")
    return {f[len(root) + 1:]: hashlib.sha256(fs.cat_file(f)).hexdigest() for f in sorted(fs.find(root))}
