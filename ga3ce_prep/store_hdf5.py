"""`export --format hdf5`: the store's arrays in one HDF5 file, for trainers that read HDF5.

Same names, shapes and dtypes as the Zarr store (docs/store.md): groups `frames/`, `objects/`,
`failures/`; strings as UTF-8 variable-length strings; `frames/split`, `frames/scene` and the
`frames/*_source` arrays carry their names in the attribute "names" (JSON list); the root attribute
"attrs" holds the store's root attributes as JSON. Written to a temporary file and renamed into
place.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .store import open_store


def export_hdf5(store: str | Path, out: str | Path) -> Path:
    """Write the store's arrays to `out` (.h5); returns its path."""
    import h5py

    s = open_store(store)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        with h5py.File(tmp, "w") as f:
            for gname, arrays in (("frames", s.frames), ("objects", s.objects), ("failures", s.failures)):
                g = f.create_group(gname)
                for name, a in arrays.items():
                    a = np.asarray(a)
                    if a.dtype.kind in "UOT":
                        g.create_dataset(name, data=a.astype(object), dtype=h5py.string_dtype())
                    else:
                        g.create_dataset(name, data=a, compression="gzip" if a.size > 4096 else None)
            f["frames/split"].attrs["names"] = json.dumps(s.split_names)
            f["frames/scene"].attrs["names"] = json.dumps(s.scene_names)
            for stage, names in s.source_names.items():
                f[f"frames/{stage}_source"].attrs["names"] = json.dumps(names)
            f.attrs["attrs"] = json.dumps(s.attrs)
            f.attrs["schema_version"] = str(s.attrs.get("schema_version", ""))
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out
