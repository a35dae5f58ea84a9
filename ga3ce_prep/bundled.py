"""The files the package carries beside its code, read with `importlib.resources` so that an
installed wheel finds them as a checkout does: the pipeline files (`ga3ce_prep/pipelines/*.yaml`,
the bundled names of `ga3ce-prep run --pipeline NAME`) and the JSON schemas
(`ga3ce_prep/schemas/`: the pipeline file's and the store's root attributes')."""
from __future__ import annotations

import atexit
import json
from contextlib import ExitStack
from importlib.resources import as_file, files
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any

_KEEP = ExitStack()  # files extracted from a zipped package stay until the process exits
atexit.register(_KEEP.close)


def _folder(name: str) -> Traversable:
    return files("ga3ce_prep").joinpath(name)


def _as_path(resource: Traversable) -> Path:
    """A real file for a resource: itself in an installed or checked-out package, else a copy."""
    if isinstance(resource, Path):
        return resource
    return Path(_KEEP.enter_context(as_file(resource)))


def pipeline_names() -> list[str]:
    """The bundled pipelines' names (`synthetic`, `gfie`, ...), sorted."""
    return sorted(p.name[: -len(".yaml")] for p in _folder("pipelines").iterdir() if p.name.endswith(".yaml"))


def pipeline_file(name: str) -> Path | None:
    """The bundled pipeline `name` (without `.yaml`) as a file; None if there is none."""
    resource = _folder("pipelines").joinpath(f"{name}.yaml")
    return _as_path(resource) if name in pipeline_names() else None


def name_of(path: str | Path) -> str | None:
    """The bundled name of the pipeline file at `path` if it is one of this package's, else None."""
    name = Path(path).stem
    bundled_file = pipeline_file(name) if Path(path).suffix == ".yaml" else None
    return name if bundled_file is not None and bundled_file.resolve() == Path(path).resolve() else None


def pipeline_text(name: str) -> str:
    """The bundled pipeline `name`'s YAML (KeyError naming the bundled names if there is none)."""
    if name not in pipeline_names():
        raise KeyError(f"no bundled pipeline {name!r} (bundled: {', '.join(pipeline_names())})")
    return _folder("pipelines").joinpath(f"{name}.yaml").read_text()


def schema_file(name: str) -> Traversable:
    """The schema `name` (`pipeline`, `store`): `ga3ce_prep/schemas/<name>.schema.json`."""
    return _folder("schemas").joinpath(f"{name}.schema.json")


def schema(name: str) -> dict[str, Any]:
    """The schema `name` (`pipeline`, `store`), parsed."""
    parsed: dict[str, Any] = json.loads(schema_file(name).read_text())
    return parsed
