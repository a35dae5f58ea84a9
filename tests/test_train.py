"""The training loop, checkpoints, evaluation, ablation table and CLI, on small toy stores."""
import dataclasses
import json

import pytest
import torch
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.errors import ConfigError
from ga3ce_prep.model import GA3CE, ModelConfig
from ga3ce_prep.store import StoreWriter
from ga3ce_prep.testing.toy_store import ATTRS as TOY_ATTRS
from ga3ce_prep.testing.toy_store import ToyKnobs, toy_world, write_toy_store
from ga3ce_prep.train import TrainConfig, ablate, evaluate, format_eval_table, train
from ga3ce_prep.train import trainer as trainer_module
from ga3ce_prep.train.ablate import default_rows
from ga3ce_prep.train.checkpoint import CheckpointError, load_checkpoint, run_design
from ga3ce_prep.train.evaluate import beside
from ga3ce_prep.train.trainer import run_done

torch.set_num_threads(2)
# the paper's widths with fewer layers: the training machinery is what these tests exercise
SMALL = dict(num_encoder_layers=1, num_decoder_layers=1, dim_feedforward=128, head_hidden=128)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    knobs = ToyKnobs(p_missing_pose=0.1, p_no_objects=0.1)
    return write_toy_store(tmp_path_factory.mktemp("s") / "toy.zarr", 320, seed=5, frames_per_scene=20, knobs=knobs)


def _cfg(store, out, **kw):
    base = dict(store=str(store), out=str(out), epochs=2, batch_size=16, train_frames=48, val_frames=32,
                warmup_epochs=1, progress=False, model=ModelConfig(**SMALL))
    return TrainConfig(**{**base, **kw})


def _weights(run):
    return load_checkpoint(run / "last.pt")["model"]


def _same(a, b):
    return all(torch.equal(a[k], b[k]) for k in a)


def test_training_is_deterministic_and_resumes_exactly(store, tmp_path):
    a = train(_cfg(store, tmp_path / "a", view_noise="on"))
    b = train(_cfg(store, tmp_path / "b", view_noise="on"))
    assert _same(_weights(a), _weights(b))                  # same seed, same weights
    c = train(_cfg(store, tmp_path / "c", view_noise="on", seed=1))
    assert not _same(_weights(a), _weights(c))
    # killed after one epoch, then resumed: identical to the uninterrupted run
    d = train(_cfg(store, tmp_path / "d", view_noise="on"), stop_after_epochs=1)
    assert load_checkpoint(d / "last.pt")["epoch"] == 0
    train(_cfg(store, tmp_path / "d", view_noise="on"), resume=True)
    assert _same(_weights(a), _weights(d))
    hist = (a / "history.csv").read_text().splitlines()
    assert len(hist) == 3
    assert hist[0].startswith("epoch,step,lr,train_loss,train_mae,val_mae")
    assert (a / "curves.png").stat().st_size > 1000
    assert (a / "best.pt").exists()
    cfg = json.loads((a / "config.json").read_text())
    assert cfg["view_noise_resolved"] is True
    assert cfg["lr"] == 3e-4


@pytest.mark.parametrize("w", [0.0, 1.0, 2.5])
def test_train_step_adds_the_first_pass_loss_with_its_weight(store, w):
    from ga3ce_prep.model import GA3CE, angular_loss
    from ga3ce_prep.store import open_store
    from ga3ce_prep.train.dataset import ContextDataset
    from ga3ce_prep.train.trainer import train_step
    b = ContextDataset(open_store(store), "train").batch(list(range(16)))
    torch.manual_seed(0)
    model = GA3CE(ModelConfig(output="pointer", dropout=0.0, **SMALL))   # the pointer: [g0, g]
    before = {k: v.clone() for k, v in model.state_dict().items()}
    g0, g = model(b.view, b.pose, b.head_pos, b.objects, b.mask, all_passes=True)
    total = angular_loss(g, b.gaze) + w * angular_loss(g0, b.gaze)
    grads = torch.autograd.grad(total, [p for p in model.parameters()], allow_unused=True)
    sgd = torch.optim.SGD(model.parameters(), lr=1.0)           # step = -gradient, no clipping at 1e9
    loss = train_step(model, sgd, b, b.view, lr=1.0, grad_clip=1e9, first_pass_loss=w)
    torch.testing.assert_close(loss, angular_loss(g, b.gaze).detach())   # it reports g's loss
    for (name, p), grad in zip(model.named_parameters(), grads):
        expect = before[name] - (grad if grad is not None else 0)
        torch.testing.assert_close(p.detach(), expect, atol=1e-6, rtol=1e-5, msg=name)


@pytest.mark.parametrize("output", ["regress", "pointer"])
def test_micro_batches_make_the_same_step_with_less_padding(store, output):
    from ga3ce_prep.store import open_store
    from ga3ce_prep.train.dataset import ContextDataset
    from ga3ce_prep.train.trainer import augment_objects, train_step
    b = ContextDataset(open_store(store), "train").batch(list(range(24)))
    b = augment_objects(b, torch.Generator().manual_seed(0), 0.3, 0.1, 0.0)   # holes, and frames with none
    pieces = b.split_by_count(4)
    assert sorted(torch.cat([rows for _, rows in pieces]).tolist()) == list(range(24))
    assert [int(p.mask.sum()) for p, _ in pieces] == [int(b.mask[rows].sum()) for _, rows in pieces]
    for p, rows in pieces:                                  # the same frames, objects in the same slots
        torch.testing.assert_close(p.objects, b.objects[rows][:, :p.mask.shape[1]])
        assert not b.mask[rows][:, p.mask.shape[1]:].any()
    assert sum(len(p) * p.mask.shape[1] for p, _ in pieces) < 0.8 * len(b) * b.mask.shape[1]
    steps = []
    for parts in (1, 4):
        torch.manual_seed(0)
        model = GA3CE(ModelConfig(output=output, dropout=0.0, **SMALL))
        init = [q.detach().clone() for q in model.parameters()]
        sgd = torch.optim.SGD(model.parameters(), lr=1.0)
        loss = train_step(model, sgd, b, b.view, lr=1.0, grad_clip=1e9, parts=parts)
        steps.append((loss, [q.detach().clone() for q in model.parameters()]))
    assert not all(torch.equal(a, q) for a, q in zip(init, steps[1][1]))   # the step moved the weights
    torch.testing.assert_close(steps[0][0], steps[1][0])
    for one, four in zip(steps[0][1], steps[1][1]):
        torch.testing.assert_close(one, four, atol=1e-6, rtol=1e-5)


def test_object_augmentation_off_is_the_recipe_without_it_and_on_changes_the_weights(store, tmp_path, monkeypatch):
    a = train(_cfg(store, tmp_path / "a"))                 # defaults: object_dropout 0, object_jitter 0
    with monkeypatch.context() as m:                       # the trainer without the object augmentation step
        m.setattr(trainer_module, "augment_objects", lambda b, *args: b)
        b = train(_cfg(store, tmp_path / "b"))
    assert _same(_weights(a), _weights(b))                 # bit-identical
    c = train(_cfg(store, tmp_path / "c", object_dropout=0.5))
    d = train(_cfg(store, tmp_path / "d", object_dropout=0.5))
    e = train(_cfg(store, tmp_path / "e", object_jitter=0.1))
    f = train(_cfg(store, tmp_path / "f", object_frame_dropout=0.5))
    assert _same(_weights(c), _weights(d))                 # seeded: same seed, same weights
    assert not any(_same(_weights(a), _weights(x)) for x in (c, e, f))
    cfg = json.loads((c / "config.json").read_text())
    assert (cfg["object_dropout"], cfg["object_jitter"]) == (0.5, 0.0)
    for bad in (dict(object_dropout=1.0), dict(object_frame_dropout=-0.1), dict(object_jitter=-1.0)):
        with pytest.raises(ConfigError, match="object_dropout"):
            _cfg(store, tmp_path / "g", **bad)


def test_checkpoint_is_plain_and_mismatches_are_refused(store, tmp_path):
    run = train(_cfg(store, tmp_path / "r", epochs=1))
    ck = torch.load(run / "last.pt", weights_only=True)    # tensors and plain types only
    assert ck["config"]["model"]["rotation"] == "cyclotorsion"
    assert "optimizer" in ck
    assert "optimizer" not in torch.load(run / "best.pt", weights_only=True)
    with pytest.raises(CheckpointError, match="--resume"):
        train(_cfg(store, tmp_path / "r", epochs=1))
    with pytest.raises(CheckpointError, match="lr: checkpoint 0.0003, now 0.001"):
        train(_cfg(store, tmp_path / "r", epochs=1, lr=1e-3), resume=True)
    other = write_toy_store(tmp_path / "other.zarr", 120, seed=9)
    with pytest.raises(CheckpointError, match="store fingerprint"):
        evaluate(other, run / "best.pt", split="test", cdf_path=None)
    r = evaluate(other, run / "best.pt", split="test", cdf_path=None, force=True)
    assert r.n_frames > 0
    # a store with no train split (CAD-120, the transfer world) is another dataset by design: Table 2
    frames, objects, scenes = toy_world(120, 9, 40, None)
    frames["split"][:] = 2
    w = StoreWriter(tmp_path / "transfer.zarr", scene_names=scenes, overwrite=True)
    w.append_frames(frames, objects)
    w.close({**TOY_ATTRS, "dataset": {"name": "toy", "root": "(generated)"}})
    t = evaluate(tmp_path / "transfer.zarr", run / "best.pt", split="test", cdf_path=None)
    forced = evaluate(tmp_path / "transfer.zarr", run / "best.pt", split="test", cdf_path=None, force=True)
    assert t.n_frames == forced.n_frames > r.n_frames
    assert t.methods["model"].mae3d == forced.methods["model"].mae3d > 0
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="cannot read"):
        load_checkpoint(tmp_path / "bad.pt")


def test_short_training_learns(tmp_path):
    # a world where the pose carries most of the signal: the head turns almost all the way
    knobs = ToyKnobs(view_noise_deg=25, head_fraction=(0.9, 1.0), face_noise=0.005, body_noise=0.005)
    st = write_toy_store(tmp_path / "easy.zarr", 600, seed=2, knobs=knobs)
    cfg = TrainConfig(store=str(st), out=str(tmp_path / "run"), epochs=3, batch_size=32, warmup_epochs=0.5,
                      progress=False, model=ModelConfig(use_objects=False, **SMALL))
    run = train(cfg)
    r = evaluate(st, run / "best.pt", split="test", cdf_path=None)
    prior = r.methods["view_prior"].mae3d
    assert r.methods["model"].mae3d < 0.85 * prior, format_eval_table(r)
    hist = load_checkpoint(run / "last.pt")["history"]
    assert hist[-1]["train_mae"] < hist[0]["train_mae"]


def test_evaluate_reports_model_and_baselines(store, tmp_path):
    run = train(_cfg(store, tmp_path / "r", epochs=1))
    r = evaluate(store, run / "best.pt", split="test", json_path=tmp_path / "e.json")
    m = r.methods
    assert set(m) == {"model", "view_prior", "head_from_pose", "snap_to_object"}
    for res in m.values():
        assert res.n == r.n_frames == res.front.n + res.back.n
        assert sum(s.n for s in res.per_scene.values()) == r.n_frames
        assert 0 < res.mae3d < 180
    assert r.beats == {k: m["model"].mae3d < m[k].mae3d
                       for k in ("view_prior", "head_from_pose", "snap_to_object")}
    written = json.loads((tmp_path / "e.json").read_text())
    assert written["methods"]["model"]["mae3d"] == pytest.approx(m["model"].mae3d)
    # the JSON keeps the keys, and their order, of the dict evaluate returned before EvalResult
    assert list(written) == ["store", "split", "checkpoint", "epoch", "no_objects_checkpoint", "compared_checkpoints",
                             "labels", "config", "dataset", "n_frames", "frames", "head_sources",
                             "head_fallback_frames", "snap_cone_deg", "head_from_pose_frames", "snapped_frames",
                             "methods", "scene_columns", "paper_rows", "beats", "ratio_to_prior", "attention",
                             "cdf_png"]                                      # attention added since
    assert list(written["methods"]["model"]) == ["n", "mae3d", "mae2d", "median3d", "front", "back", "per_scene",
                                                 "at_object", "elsewhere"]          # the last two added since
    assert (tmp_path / "e.json").read_text() == json.dumps(r.to_json(), indent=2, default=float)
    assert (run / "eval_test_cdf.png").stat().st_size > 1000
    table = format_eval_table(r)
    assert r.labels["model"] == "GA3CE (paper)"   # the default model is the paper's, named so
    assert table.splitlines()[4].startswith("GA3CE (paper) ") and " model " not in table
    for key, beats in r.beats.items():   # the table says which baselines the model does not beat
        assert (f"  beats {r.labels[key]}" in table) == beats
        assert (f"does NOT beat {r.labels[key]}" in table) == (not beats)
    # appearance only: the checkpoint reproduces the v prior exactly
    app = train(_cfg(store, tmp_path / "app", model=ModelConfig(use_context=False, **SMALL)))
    ra = evaluate(store, app / "best.pt", split="test", cdf_path=None)
    assert ra.methods["model"].mae3d == pytest.approx(ra.methods["view_prior"].mae3d, abs=1e-4)


def test_ablate_table(store, tmp_path):
    base = _cfg(store, tmp_path, epochs=1, train_frames=32)
    rows = ["appearance", "no-objects", "no-pose", "full", "ours"]   # no-pose: no paper figure
    s = ablate(base, tmp_path / "abl", rows=rows)
    assert [r["name"] for r in s["rows"]] == rows
    assert [r["label"] for r in s["rows"]][3:] == ["GA3CE (paper) (full)", "pointer-frozen (ours)"]
    assert [r["design"] for r in s["rows"]] == ["ga3ce"] * 4 + ["pointer-frozen"]   # the alias row, resolved
    assert "ours" in default_rows("ga3ce") and "ga3ce" not in default_rows("ga3ce") and "ga3ce" in default_rows("ours")
    assert s["rows"][0]["ratio"] == pytest.approx(1.0, abs=1e-5)
    t = s["table"]
    assert "Table 4" in t
    assert "Table 5" in t
    assert "19.40" in t
    assert "13.10" in t
    assert "11.10" in t
    assert ("the full model is best" in t) == s["full_best"]
    assert "The other designs" in t and "pointer-frozen (ours)" in t
    cfg = load_checkpoint(tmp_path / "abl" / "ours" / "seed0" / "best.pt")["config"]["model"]
    assert (cfg["method"], cfg["output"], cfg["pointer_g0"]) == ("pointer-frozen", "pointer", "frozen")
    assert run_design(tmp_path / "abl" / "ours" / "seed0") == "pointer-frozen"   # one home for a run's design
    assert run_design(tmp_path / "abl" / "full" / "seed0" / "best.pt") == "ga3ce" and run_design(tmp_path) is None
    assert (tmp_path / "abl" / "ablation.png").stat().st_size > 1000
    assert json.loads((tmp_path / "abl" / "ablation.json").read_text())["rows"][1]["paper_gfie"] == 13.1
    # eval of the full row scores the no-objects row beside it (what the objects add), and says so
    full, noobj = (tmp_path / "abl" / n / "seed0" / "best.pt" for n in ("full", "no-objects"))
    assert beside(full) == {"no_objects": noobj, "compare": {"ours": tmp_path / "abl" / "ours" / "seed0" / "best.pt"}}
    assert "no_objects" not in evaluate(store, full, split="test", cdf_path=None).methods   # given, never searched
    r = evaluate(store, full, split="test", cdf_path=None, **beside(full))
    assert r.no_objects_checkpoint == str(noobj)
    m = r.methods
    assert m["no_objects"].mae3d == pytest.approx(s["rows"][1]["mae3d"], abs=1e-9)
    assert m["ours"].mae3d == pytest.approx(s["rows"][4]["mae3d"], abs=1e-9)   # ours beside it, by name
    assert r.labels["ours"] == "pointer-frozen (ours)" and r.beats["ours"] == (m["model"].mae3d < m["ours"].mae3d)
    assert m["model"].mae3d == pytest.approx(s["rows"][3]["mae3d"], abs=1e-9)
    assert r.beats["no_objects"] == (m["model"].mae3d < m["no_objects"].mae3d)
    table = format_eval_table(r)
    assert "no objects (app. + pose)" in table
    assert ("objects add" if r.beats["no_objects"] else "objects cost") in table
    assert "no_objects" not in evaluate(store, full, split="test", cdf_path=None, no_objects=None).methods
    assert "no_objects" not in evaluate(store, noobj, split="test", cdf_path=None).methods
    res = CliRunner().invoke(cli, ["eval", "--store", str(store), "--checkpoint", str(full), "--cdf", "none",
                                   "--no-scenes"])
    assert res.exit_code == 0, res.output
    assert f"{m['no_objects'].mae3d:.2f}" in res.output and "no objects (app. + pose)" in res.output
    # rerunning reuses the finished runs
    mtime = (tmp_path / "abl" / "full" / "seed0" / "best.pt").stat().st_mtime
    ablate(base, tmp_path / "abl", rows=["full"])
    assert (tmp_path / "abl" / "full" / "seed0" / "best.pt").stat().st_mtime == mtime


def test_cli_train_eval(store, tmp_path):
    runner = CliRunner()
    out = tmp_path / "cli"
    res = runner.invoke(cli, ["train", "--store", str(store), "--out", str(out), "--epochs", "1",
                              "--train-frames", "32", "--val-frames", "16", "--no-progress", "--ablation", "no-ga3ce",
                              "--model-set", "cone_bias_scale=2", "--model-set", "num_encoder_layers=1",
                              "--model-set", "num_decoder_layers=1"])
    assert res.exit_code == 0, res.output
    ck = load_checkpoint(out / "best.pt")
    assert ck["config"]["model"]["rotation"] == "none"
    assert ck["config"]["model"]["encoding"] == "standard"
    assert ck["config"]["model"]["cone_bias_scale"] == 2
    res = runner.invoke(cli, ["eval", "--store", str(store), "--checkpoint", str(out / "best.pt"), "--cdf", "none"])
    assert res.exit_code == 0, res.output
    assert "GA3CE (paper), rotation=none, encoding=standard " in res.output and "(model)" not in res.output
    assert "head direction from pose" in res.output
    # --model ours: the alias of our current design, recorded and named in the table by its fixed name
    res = runner.invoke(cli, ["train", "--store", str(store), "--out", str(tmp_path / "ours"), "--epochs", "1",
                              "--train-frames", "32", "--val-frames", "16", "--no-progress", "--model", "ours",
                              "--model-set", "num_encoder_layers=1", "--model-set", "num_decoder_layers=1"])
    assert res.exit_code == 0, res.output
    cfg = load_checkpoint(tmp_path / "ours" / "best.pt")["config"]["model"]
    assert (cfg["method"], cfg["output"]) == ("pointer-frozen", "pointer")
    res = runner.invoke(cli, ["eval", "--store", str(store), "--checkpoint", str(tmp_path / "ours" / "best.pt"),
                              "--cdf", "none", "--no-scenes"])
    assert res.exit_code == 0, res.output
    assert "\npointer-frozen (ours) " in res.output and "GA3CE (paper)" not in res.output
    res = runner.invoke(cli, ["train", "--store", str(store), "--out", str(out), "--model", "ours",
                              "--ablation", "ga3ce"])
    assert res.exit_code != 0 and "drop --model ours" in res.output
    res = runner.invoke(cli, ["train", "--store", str(store), "--out", str(out), "--ablation", "no-ga3ce",
                              "--rotation", "axis_angle"])
    assert res.exit_code != 0
    assert "--ablation no-ga3ce" in res.output
    res = runner.invoke(cli, ["ablate", "--help"])
    assert res.exit_code == 0
    assert "no-cyclotorsion" in res.output


def test_cli_recipe_options_are_the_config_fields():
    from ga3ce_prep.train.cli import ablate as ablate_cmd
    from ga3ce_prep.train.cli import train as train_cmd
    d = TrainConfig()
    for cmd in (train_cmd, ablate_cmd):
        params = {p.name: p for p in cmd.params}
        assert {f.name for f in dataclasses.fields(TrainConfig)} - {"model"} <= set(params)
        for name, p in params.items():
            if hasattr(d, name) and name not in ("store", "out", "n_max"):   # n_max: batch | auto | N
                assert p.default == getattr(d, name), name
    res = CliRunner().invoke(cli, ["train", "--help"])
    assert "--batching [mixed|sorted|shuffled]" in res.output
    assert "--no-progress" in res.output
    assert "no-ga3ce" in res.output
    text = " ".join(res.output.split())
    assert "ga3ce = GA3CE (paper)" in text and "[default: ga3ce]" in text
    assert TrainConfig().model.method == "ga3ce" and TrainConfig().model.output == "regress"   # the paper's


def test_frozen_g0_is_the_no_objects_twin(store, tmp_path):
    """pointer_g0 frozen: the run trains the no-objects model first (g0/, same recipe and seed: the
    very weights of the no-objects row), keeps them, and trains the pointer alone on top."""
    ours = ModelConfig.for_method("ours", pointer_g0="frozen", **SMALL)
    run = train(_cfg(store, tmp_path / "ours", model=ours))
    twin = train(_cfg(store, tmp_path / "bare", model=ModelConfig(use_objects=False, **SMALL)))
    g0, bare, final = _weights(run / "g0"), _weights(twin), _weights(run)
    assert _same(g0, bare)
    assert _same(bare, {k: final[k] for k in bare})                       # frozen: unchanged by the pointer stage
    torch.manual_seed(0)                                                  # the run's initial weights
    init = GA3CE(ours).state_dict()
    assert all(not torch.equal(final[k], v) for k, v in init.items() if k.startswith("pointer."))   # trained
    r = evaluate(store, run / "best.pt", split="test", cdf_path=None,
                 no_objects=run / "g0" / "best.pt")
    name = "pointer-frozen (ours)"   # ours names pointer-frozen today (tests/test_designs.py)
    assert r.labels == {**r.labels, "model": name, "no_objects": "no objects (app. + pose)"}
    assert run_done(run, 2) and run_done(run / "g0", 2)
    # resumed when finished, the g0 stage is reused; resumed with more epochs, both continue
    mtime = (run / "g0" / "best.pt").stat().st_mtime
    train(_cfg(store, tmp_path / "ours", model=ours), resume=True)
    assert (run / "g0" / "best.pt").stat().st_mtime == mtime
    train(_cfg(store, tmp_path / "ours", model=ours, epochs=3), resume=True, force=True)
    assert run_done(run / "g0", 3) and run_done(run, 3)
