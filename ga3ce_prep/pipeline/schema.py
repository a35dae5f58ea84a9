"""The JSON Schema of the pipeline files, generated from the code that reads them: each backend's
`Params` dataclass (`ga3ce_prep.stages.BACKENDS`), the run settings (`RunParams`) and the dataset
adapters (`ga3ce_prep.datasets.ADAPTERS`).

`ga3ce_prep/schemas/pipeline.schema.json` is its committed copy, shipped in the package (read with
importlib.resources: ga3ce_prep/bundled.py), for editors and other tools, and the copy the loader
validates against; the defaults and file parameters the loader fills in come from the
dataclasses themselves. `make schema` rewrites it; a test fails while it is stale.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..params import json_schema, param

# the package's copy, which `make schema` rewrites (in a checkout)
SCHEMA_FILE = Path(__file__).resolve().parent.parent / "schemas" / "pipeline.schema.json"


@dataclass(frozen=True, kw_only=True)
class RunParams:
    """The pipeline file's `run` section."""

    shard_size: int = param(32, minimum=1)  # frames per shard (the unit of caching and of dask tasks)
    cache_depth_maps: bool = (
        # keep completed depth maps in the cache (1.5 MB per 640x480
        # frame); off: recompute them when a downstream stage needs them
        False)


def _stage_schema(stage: str, names: list[str]) -> dict[str, Any]:
    """One stage: a backend name, and its parameters validated by that backend's `$defs` entry."""
    return {
        "type": "object", "required": ["backend"], "additionalProperties": False,
        "properties": {"backend": {"enum": names}, "params": {"type": "object", "default": {}}},
        "allOf": [{"if": {"required": ["backend"], "properties": {"backend": {"const": n}}},
                   "then": {"properties": {"params": {"$ref": f"#/$defs/{stage}.{n}"}}}} for n in names],
    }


def build_schema() -> dict[str, Any]:
    """The whole pipeline schema (draft 2020-12). Imports every backend's module."""
    from ..datasets import ADAPTERS
    from ..stages import BACKENDS, STAGES, backend_class

    defs: dict[str, Any] = {}
    for key in BACKENDS:
        stage, name = key.split("/")
        defs[f"{stage}.{name}"] = json_schema(backend_class(stage, name).Params)
    for stage in STAGES:
        defs[stage] = _stage_schema(stage, [k.split("/")[1] for k in BACKENDS if k.startswith(stage + "/")])
    run = json_schema(RunParams)
    run["default"] = {}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://github.com/ga3ce-prep/ga3ce-prep/ga3ce_prep/schemas/pipeline.schema.json",
        "title": "ga3ce-prep pipeline file",
        "description": "One preprocessing pipeline: the dataset adapter, a backend and its parameters per stage, "
                       "run settings. Generated from the code (ga3ce_prep/pipeline/schema.py: `make schema`); "
                       "do not edit by hand. Defaults are those of the backends' Params dataclasses; "
                       "parameters marked x-file name files ({data} = the --data root; relative paths are "
                       "relative to the current directory). docs/pipeline.md explains each stage.",
        "type": "object",
        "required": ["name", "dataset", "stages"],
        "additionalProperties": False,
        "properties": {
            "name": {"type": "string", "minLength": 1},
            "description": {"type": "string"},
            "dataset": {
                "type": "object", "required": ["format"], "additionalProperties": False,
                "properties": {
                    "format": {"enum": list(ADAPTERS), "description": "the adapter (ga3ce_prep/datasets)"},
                    "options": {"type": "object", "default": {},
                                "description": "adapter keyword options (docs/datasets.md)"},
                },
            },
            "stages": {
                "type": "object", "required": [s for s in STAGES if s != "input"], "additionalProperties": False,
                "properties": {s: {"$ref": f"#/$defs/{s}"} for s in STAGES},
            },
            "run": run,
        },
        "$defs": defs,
    }


def schema_text() -> str:
    return json.dumps(build_schema(), indent=2) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="Generate ga3ce_prep/schemas/pipeline.schema.json from the backends' Params.")
    ap.add_argument("--write", action="store_true", help=f"rewrite {SCHEMA_FILE}")
    ap.add_argument("--check", action="store_true", help="exit 1 if the committed file is stale")
    args = ap.parse_args(argv)
    text = schema_text()
    if args.write:
        SCHEMA_FILE.write_text(text)
        print(f"wrote {SCHEMA_FILE}")
    elif args.check:
        if SCHEMA_FILE.read_text() != text:
            print(f"{SCHEMA_FILE} is stale: run `make schema`", file=sys.stderr)
            return 1
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
