"""Pipeline files (a path, or a bundled name: `ga3ce_prep/pipelines/<name>.yaml`): load, validate
against ga3ce_prep/schemas/pipeline.schema.json (generated from the backends' `Params` dataclasses:
pipeline/schema.py), fill in defaults, resolve file parameters, and check everything a run needs
before any work.

Each backend's `Params` dataclass is the one source of its parameters: the defaults filled in and
the file parameters resolved here are read from it (`params.defaults`, `params.file_fields`), not
from the schema, which is its generated copy for editors and validation.

Every error names the pipeline key at fault (e.g. `stages.view.params.mean_error_deg`) and the fix.
File parameters ("x-file" in the schema) may use `{data}` for the dataset root (`--data`) and
`{models}` for the folder of the user's model files (`--models`, else $GA3CE_MODEL_DIR, else
./models); other relative paths are relative to the current directory.
"""
from __future__ import annotations

import copy
import hashlib
import json
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from .. import bundled
from ..errors import ConfigError, ModelFileError
from ..params import defaults, file_fields, from_dict, load_yaml
from ..stages import STAGES, backend_class, upstream_of
from ..stages.base import Backend, BackendContext
from ..weights.folder import FileStatus
from .schema import RunParams


@dataclass
class StageConfig:
    """One stage as configured: backend name, its parameters as the backend's typed `Params`
    (defaults filled, files resolved; built once, here, and handed to the backend as they are), the
    same as a plain mapping, and which parameters name data files and model files."""

    stage: str
    backend: str
    p: Any                                   # the backend's Params instance
    data_files: dict[str, Path] = field(default_factory=dict)
    model_files: dict[str, Path] = field(default_factory=dict)

    @property
    def params(self) -> dict[str, Any]:
        """The parameters as a mapping (field name -> value; files as absolute Paths)."""
        return {f.name: getattr(self.p, f.name) for f in fields(self.p)}

    def make(self, data_root: Path) -> Backend:
        """An instance of the backend (imports its module)."""
        return backend_class(self.stage, self.backend)(self.p, BackendContext(Path(data_root)))


@dataclass
class PipelineConfig:
    """A validated pipeline. `config` is the effective configuration (defaults filled in) that goes
    into the store's provenance; `sha256` hashes the pipeline file as written."""

    name: str
    file: str
    sha256: str
    dataset_format: str
    dataset_options: dict[str, Any]
    stages: dict[str, StageConfig]
    shard_size: int
    cache_depth_maps: bool
    config: dict[str, Any]
    upstream: dict[str, tuple[str, ...]]  # each stage's effective upstream (stages.upstream_of)
    models: Path | None = None  # the folder `{models}` stood for


def schema() -> dict[str, Any]:
    return bundled.schema("pipeline")


def _key(path) -> str:
    return ".".join(str(p) for p in path) or "(top level)"


def resolve_pipeline_path(pipeline: str | Path) -> Path:
    """A pipeline file path; a bare name like "gfie" (no file of that name here) means the bundled
    pipeline ga3ce_prep/pipelines/gfie.yaml."""
    p = Path(pipeline)
    if p.is_file():
        return p
    bundled_file = bundled.pipeline_file(str(pipeline)) if p.suffix == "" and p.name == str(pipeline) else None
    if bundled_file is not None:
        return bundled_file
    raise ConfigError(f"pipeline file {p} not found (bundled pipelines: {', '.join(bundled.pipeline_names())})")


def _parse_override(item: str) -> tuple[list[str], Any]:
    if "=" not in item:
        raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. stages.view.params.mean_error_deg=30")
    key, value = item.split("=", 1)
    try:
        return key.strip().split("."), load_yaml(value)
    except yaml.YAMLError as e:
        raise ConfigError(f"--set {item!r}: the value is not valid YAML ({e})") from None


def apply_overrides(raw: dict[str, Any], overrides: list[str] | dict[str, Any] | None) -> dict[str, Any]:
    """Copy of raw with dotted-key overrides applied ("stages.view.params.mean_error_deg=30" or a dict)."""
    raw = copy.deepcopy(raw)
    items = (list(overrides.items()) if isinstance(overrides, dict)
             else [_parse_override(o) for o in overrides or []])
    for key, value in items:
        parts = key.split(".") if isinstance(key, str) else key
        node = raw
        for part in parts[:-1]:
            if not isinstance(node.setdefault(part, {}), dict):
                raise ConfigError(f"override {'.'.join(parts)}: {part} is not a mapping")
            node = node[part]
        node[parts[-1]] = value
    return raw


def validate(raw: Any, where: str) -> None:
    """JSON-Schema validation; ConfigError listing every error by its key."""
    import jsonschema

    v = jsonschema.Draft202012Validator(schema())
    errors = sorted(v.iter_errors(raw), key=lambda e: (list(map(str, e.absolute_path)), e.message))
    if not errors:
        return
    # an `if/then` branch reports the params error itself; drop the generic ones
    lines = [f"  {_key(e.absolute_path)}: {e.message}" for e in errors[:12]]
    more = f"\n  ... and {len(errors) - 12} more" if len(errors) > 12 else ""
    raise ConfigError(f"{where} is not a valid pipeline (ga3ce_prep/schemas/pipeline.schema.json):\n"
                      + "\n".join(lines) + more)


def model_dir(models: str | Path | None = None) -> Path:
    """The folder `{models}` stands for: `models`, else $GA3CE_MODEL_DIR, else ./models."""
    return Path(models or os.environ.get("GA3CE_MODEL_DIR") or "models").resolve()


def _resolve(value: str, data_root: Path, models: Path) -> Path:
    """A file parameter as an absolute path: `{data}` and `{models}` replaced, relative to the
    current directory otherwise."""
    return Path(os.path.abspath(str(value).replace("{data}", str(data_root)).replace("{models}", str(models))))


def load_pipeline(pipeline: str | Path | dict[str, Any], data_root: str | Path,
                  overrides: list[str] | dict[str, Any] | None = None, check_files: bool = True,
                  models: str | Path | None = None) -> PipelineConfig:
    """Load and validate a pipeline (a file, a bundled name, or an already-parsed dict).

    Fills in defaults, resolves file parameters against data_root and the model folder (`models`,
    module docstring), and (check_files) checks that
    every backend is available and every named file exists: ConfigError/ModelFileError otherwise,
    before any work.
    """
    data_root = Path(data_root).resolve()
    if isinstance(pipeline, dict):
        raw, where = pipeline, "pipeline"
        text = json.dumps(pipeline, sort_keys=True).encode()
    else:
        path = resolve_pipeline_path(pipeline)
        text = path.read_bytes()
        where = os.path.abspath(path)  # the provenance records it: absolute, as every path there
        try:
            raw = load_yaml(text)
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML: {e}") from None
    raw = apply_overrides(raw if isinstance(raw, dict) else {}, overrides) if raw is not None else raw
    validate(raw, where)
    cfg = copy.deepcopy(raw)
    cfg.setdefault("run", {})
    cfg["run"] = {**defaults(RunParams), **cfg["run"]}
    cfg["dataset"].setdefault("options", {})
    cfg["stages"].setdefault("input", {"backend": "check"})
    stages: dict[str, StageConfig] = {}
    for stage in STAGES:
        sc = cfg["stages"][stage]
        backend = sc["backend"]
        cls = backend_class(stage, backend).Params
        params = {**defaults(cls), **sc.get("params", {})}
        sc["params"] = params
        data_files: dict[str, Path] = {}
        model_files: dict[str, Path] = {}
        resolved = dict(params)
        for name, spec in file_fields(cls).items():
            kind = spec["x-file"]
            if name in params and params[name] is not None:
                p = _resolve(params[name], data_root, model_dir(models))
                resolved[name] = p
                if "{" not in str(params[name]):  # the effective configuration records it absolute
                    params[name] = str(p)
                (model_files if kind == "model" else data_files)[name] = p
        stages[stage] = StageConfig(stage, backend, from_dict(cls, resolved, f"stages.{stage}.params"), data_files,
                                    model_files)
    conf = PipelineConfig(
        name=cfg["name"], file=where, sha256=hashlib.sha256(text).hexdigest(),
        dataset_format=cfg["dataset"]["format"], dataset_options=dict(cfg["dataset"]["options"]),
        stages=stages, shard_size=int(cfg["run"]["shard_size"]),
        cache_depth_maps=bool(cfg["run"]["cache_depth_maps"]), config=cfg,
        upstream=upstream_of({s: sc.backend for s, sc in stages.items()}), models=model_dir(models))
    if check_files:
        check_pipeline(conf, data_root)
    return conf


def models_check_hint(conf: PipelineConfig) -> str:
    """The `ga3ce-prep models check` command that lists the pipeline's whole model folder."""
    pipeline = "" if conf.file == "pipeline" else f" --pipeline {bundled.name_of(conf.file) or conf.file}"
    return f"`ga3ce-prep models check --models {conf.models or model_dir()}{pipeline}` lists what the folder holds"


def check_pipeline(conf: PipelineConfig, data_root: Path) -> list[Backend]:
    """Before any work: model files exist, backends are available, each backend's own check
    (data files readable). Returns the backend instances."""
    missing = missing_lines(conf, data_root)
    if missing:
        raise ModelFileError("\n  ".join([*missing, models_check_hint(conf)]))
    backends = []
    for sc in conf.stages.values():
        b = sc.make(data_root)
        b.check()
        backends.append(b)
    return backends


def stage_files(sc: StageConfig, data_root: Path) -> list[FileStatus]:
    """Every model file the stage reads: its model-file parameters and the files its backend reads
    beside them (`Backend.side_files`), not yet checked."""
    fields = file_fields(backend_class(sc.stage, sc.backend).Params)
    files = [FileStatus(f"stages.{sc.stage}.params.{name}", Path(path), sc.stage, fields[name].get("x-hint", ""))
             for name, path in sc.model_files.items()]
    for what, path in sc.make(data_root).side_files().items():
        files.append(FileStatus(f"stages.{sc.stage} ({what})", Path(path), sc.stage, ""))
    return files


def missing_lines(conf: PipelineConfig, data_root: Path) -> list[str]:
    """One line per missing model file of the pipeline: its key, its path and how to make it."""
    return [f"{f.key}: model file {f.path} does not exist; {f.make}"
            for sc in conf.stages.values() for f in stage_files(sc, data_root) if not f.path.is_file()]


def check_stage(sc: StageConfig, data_root: Path) -> list[FileStatus]:
    """The stage's model files with their status: missing; present while another file of the stage
    is missing; else verified or fails, as the backend's own check says (before any run's work)."""
    files = stage_files(sc, data_root)
    if not files:
        return []
    for f in files:
        f.status = "present" if f.path.is_file() else "missing"
    if all(f.status == "present" for f in files):
        try:
            sc.make(data_root).check()
            status, detail = "verified", ""
        except Exception as e:  # whatever the check raises, the file fails it
            status, detail = "failing", str(e)
        for f in files:
            f.status, f.detail = status, detail
    else:
        for f in files:
            if f.status == "present":
                f.detail = "not checked: " + ", ".join(g.path.name for g in files if g.status == "missing") + " missing"
    return files
