"""Dataset adapters: one module per on-disk format, each yielding `FrameRef`s.

Adapters validate a dataset's structure (layout, annotation columns) and raise DatasetFormatError
naming the file, the field and the fix before any work starts; per-frame problems surface later,
when a stage loads the frame. Adapters never run a model.
"""
from __future__ import annotations

import importlib
import inspect
from pathlib import Path

from ..errors import ConfigError
from .base import DatasetAdapter

# name -> "module:class"
ADAPTERS: dict[str, str] = {
    "gfie": "ga3ce_prep.datasets.gfie:GFIEAdapter",
    "cad120": "ga3ce_prep.datasets.cad120:CAD120Adapter",
    "gafa": "ga3ce_prep.datasets.gafa:GAFAAdapter",
    "folder": "ga3ce_prep.datasets.folder:FolderAdapter",
}


def open_dataset(name: str, root: str | Path, **options) -> DatasetAdapter:
    """The adapter `name` over the dataset at `root` (options are adapter-specific: ConfigError
    naming `dataset.options.<name>` for one it does not take, or a value it refuses)."""
    if name not in ADAPTERS:
        raise ConfigError(f"dataset.format: unknown dataset format {name!r}; known: {', '.join(ADAPTERS)}")
    module, cls_name = ADAPTERS[name].split(":")
    cls = getattr(importlib.import_module(module), cls_name)
    known = [p for p in inspect.signature(cls.__init__).parameters if p not in ("self", "root")]
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ConfigError(f"dataset.options.{unknown[0]}: the {name} adapter has no such option; its options: "
                          f"{', '.join(known) or 'none'} (docs/datasets.md)")
    return cls(root, **options)


def open_store_dataset(provenance: dict, data: str | Path | None = None) -> DatasetAdapter:
    """The adapter of the dataset a store was made from: its provenance (`store.attrs["dataset"]`:
    name, root, options), with `data` for the root when the dataset has moved. Raises what
    `open_dataset` raises (Ga3ceError, KeyError for an unknown format, OSError, TypeError)."""
    return open_dataset(str(provenance.get("name", "")), data or provenance.get("root", ""),
                        **(provenance.get("options") or {}))


__all__ = ["ADAPTERS", "DatasetAdapter", "open_dataset", "open_store_dataset"]
