"""Designs have fixed names: `ours` is an alias resolved to a fixed design wherever a model is made,
recorded, named in a table or read back; a fixed name's config never changes; checkpoints that
stored the alias (before the fixed names) load as the design the alias named then."""
import json
import logging

import pytest
import torch
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.model import ALIASES, GA3CE, METHODS, ModelConfig, model_label, resolve
from ga3ce_prep.model.methods import ALIAS_HISTORY, aliases_of, saved_design
from ga3ce_prep.train import TrainConfig
from ga3ce_prep.train.ablate import BY_NAME, ablate, default_rows, row_label
from ga3ce_prep.train.checkpoint import build_model, check_checkpoint, load_checkpoint, save_checkpoint

TINY = dict(num_encoder_layers=1, num_decoder_layers=1, dim_feedforward=32, head_hidden=32)

# Every ModelConfig value of each fixed design. A design's name never changes meaning: if this test
# fails because a default moved, the new values are a new design with a new name (model/methods.py),
# and `ours` may then name it; the old name keeps these values.
COMMON = {
    "rotation": "cyclotorsion", "encoding": "d3", "use_pose": True, "use_objects": True, "use_context": True,
    "cone_bias": True, "cone_bias_scale": 1.0, "pointer_kappa": 300.0, "d_model": 256, "n_heads": 2,
    "dim_feedforward": 512, "num_encoder_layers": 3, "num_decoder_layers": 3, "dropout": 0.1, "norm_first": False,
    "head_hidden": 512, "view_width": 106, "joint_width": 10, "joint_dir_width": 6, "object_dir_width": 128,
    "view_scale": 1.0, "direction_scale": 0.25, "pose_distance_scale": 0.05, "object_distance_scale": 0.3,
    "pose_position_scale": 0.05, "object_position_scale": 0.15, "fourier_seed": 0,
}
PINNED = {
    "ga3ce": {**COMMON, "method": "ga3ce", "output": "regress", "pointer_g0": "joint"},
    "pointer-joint": {**COMMON, "method": "pointer-joint", "output": "pointer", "pointer_g0": "joint"},
    "pointer-frozen": {**COMMON, "method": "pointer-frozen", "output": "pointer", "pointer_g0": "frozen"},
}


@pytest.mark.parametrize("name", list(PINNED))
def test_a_fixed_name_keeps_its_values(name):
    d = ModelConfig.for_method(name).to_dict()
    d.pop("head_width_pair")   # the skeleton's joint pair, not a design choice
    assert d == PINNED[name], f"design {name!r} changed meaning: give the new values a new name"
    assert set(METHODS) == set(PINNED)


def test_ours_is_an_alias_resolved_to_its_design():
    assert ALIASES == {"ours": "pointer-frozen"}
    assert resolve("ours") == "pointer-frozen" and resolve("pointer-joint") == "pointer-joint"
    assert resolve("ga3ce") == "ga3ce" and aliases_of("pointer-frozen") == ["ours"] and aliases_of("ga3ce") == []
    with pytest.raises(ValueError, match="choose one of ga3ce, pointer-joint, pointer-frozen, ours"):
        resolve("nerfacto")
    # the config records the design, never the alias, however it is made
    assert ModelConfig.for_method("ours").method == "pointer-frozen"
    assert ModelConfig(method="ours").method == "pointer-frozen"
    assert ModelConfig.for_method("ours").to_dict() == ModelConfig.for_method("pointer-frozen").to_dict()
    assert ModelConfig.for_method("ours", use_pose=False).to_dict()["method"] == "pointer-frozen"
    # the last design the alias has named is the one it names today
    assert ALIAS_HISTORY["ours"][-1][0] == ALIASES["ours"]
    assert [d for d, _, _ in ALIAS_HISTORY["ours"]] == ["pointer-joint", "pointer-frozen"]


def test_tables_name_the_design_and_say_which_is_ours():
    assert model_label(ModelConfig.for_method("ours")) == "pointer-frozen (ours)"
    assert model_label(ModelConfig.for_method("pointer-joint")) == "pointer-joint"
    assert model_label(ModelConfig.for_method("ga3ce")) == "GA3CE (paper)"
    assert model_label(ModelConfig.for_method("ours", use_pose=False)) == "pointer-frozen (ours), use_pose=False"
    assert model_label(ModelConfig.for_method("pointer-joint", pointer_g0="frozen")) == \
        "pointer-joint, pointer_g0=frozen"
    # ablate: the alias row trains the design it names today and is labelled by it
    assert BY_NAME["ours"].design == "pointer-frozen" and BY_NAME["pointer-joint"].design == "pointer-joint"
    assert BY_NAME["full"].design is None
    assert row_label(BY_NAME["ours"], ModelConfig.for_method("ga3ce")) == "pointer-frozen (ours)"
    assert row_label(BY_NAME["full"], ModelConfig.for_method("ours")) == "pointer-frozen (ours) (full)"
    paper = ["appearance", "no-objects", "no-pose", "no-ga3ce", "full", "no-egocentric", "no-cyclotorsion", "no-d3"]
    assert default_rows("ga3ce") == [*paper, "ours"]
    assert default_rows("ours") == default_rows("pointer-frozen") == [*paper, "ga3ce"]
    assert default_rows("pointer-joint") == [*paper, "ga3ce", "ours"]


@pytest.mark.parametrize("saved, design", [
    ({"method": "ours", "output": "pointer", "pointer_g0": "joint"}, "pointer-joint"),     # ours until 59f75a3
    ({"method": "ours", "output": "pointer", "pointer_g0": "frozen"}, "pointer-frozen"),   # ours since 59f75a3
    ({"method": "ours", "output": "pointer"}, "pointer-joint"),      # before pointer_g0 existed: g0 was joint
    ({"output": "pointer"}, "pointer-joint"),                         # before methods had names
    ({"output": "regress"}, "ga3ce"),
    ({}, "ga3ce"),                                                    # before the pointer existed
    ({"method": "ga3ce", "output": "pointer", "pointer_g0": "frozen"}, "ga3ce"),   # a design stays itself
])
def test_saved_configs_load_as_the_design_they_were(saved, design, caplog):
    with caplog.at_level(logging.WARNING, logger="ga3ce_prep.model"):
        assert ModelConfig.from_dict(saved).method == design
    assert not caplog.records


def test_an_alias_that_cannot_be_told_reads_as_todays_design_with_a_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="ga3ce_prep.model"):
        assert ModelConfig.from_dict({"method": "ours", "output": "regress"}).method == "pointer-frozen"
    assert "matches none of the designs 'ours' has named" in caplog.text
    assert saved_design("pointer-joint", {}) == "pointer-joint"
    with pytest.raises(ValueError, match="unknown model"):
        saved_design("theirs", {})


def test_an_old_checkpoint_that_stored_ours_loads_as_its_design(tmp_path):
    """A checkpoint written when `ours` was the joint pointer (method "ours" in its config) loads,
    builds and is named as pointer-joint; resuming it with the design's config finds no difference."""
    cfg = ModelConfig.for_method("pointer-joint", **TINY)
    weights = GA3CE(cfg).state_dict()
    saved = {**cfg.to_dict(), "method": "ours"}
    train = {**TrainConfig().to_dict(), "model": saved}
    save_checkpoint(tmp_path / "old.pt", {"epoch": 0, "model": weights, "config": train, "history": [],
                                          "best_val": 1.0, "store_fingerprint": "x"})
    ck = load_checkpoint(tmp_path / "old.pt")
    model = build_model(ck)
    assert model.config.method == "pointer-joint" and model.config.pointer_g0 == "joint"
    assert model_label(model.config) == "pointer-joint"
    assert all(torch.equal(model.state_dict()[k], v) for k, v in weights.items())
    now = {**TrainConfig().to_dict(), "model": cfg.to_dict()}
    assert check_checkpoint(ck, tmp_path / "old.pt", "x", now) == []
    moved = {**now, "model": ModelConfig.for_method("ours", **TINY).to_dict()}   # ours today: another design
    assert check_checkpoint(ck, tmp_path / "old.pt", "x", moved, force=True) == \
        ["model.method: checkpoint 'pointer-joint', now 'pointer-frozen'",
         "model.pointer_g0: checkpoint 'joint', now 'frozen'"]


def test_ablate_refuses_a_row_folder_of_another_design(tmp_path):
    """OUT/ours/seed0 trained when ours named pointer-joint is not reused as today's ours; naming
    the same design twice (alias and name) is refused; both before any training."""
    base = TrainConfig(store=str(tmp_path / "none.zarr"), out=str(tmp_path), epochs=1,
                       model=ModelConfig.for_method("ga3ce"))
    run = tmp_path / "abl" / "ours" / "seed0"
    run.mkdir(parents=True)
    old = {**ModelConfig.for_method("pointer-joint").to_dict(), "method": "ours"}
    (run / "config.json").write_text(json.dumps({**base.to_dict(), "model": old}))
    with pytest.raises(Exception, match="holds 'pointer-joint', but the row 'ours' trains 'pointer-frozen'"):
        ablate(base, tmp_path / "abl", rows=["ours"])
    with pytest.raises(ValueError, match="same design twice"):
        ablate(base, tmp_path / "abl", rows=["ours", "pointer-frozen"])


def test_cli_lists_designs_and_the_alias():
    res = CliRunner().invoke(cli, ["train", "--help"])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "[ga3ce|pointer-joint|pointer-frozen|ours]" in text
    assert "ours = pointer-frozen today" in text
