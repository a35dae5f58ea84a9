"""Experiments as objects (ga3ce_prep/experiments): a World made once, arms trained unless done,
scores that match an evaluation of the same checkpoint, and one results file that names its
conditions."""
import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ga3ce_prep.errors import ConfigError
from ga3ce_prep.experiments import Arm, Experiment, World, format_results, mae_table, run_experiment
from ga3ce_prep.experiments.cli import experiment as experiment_cli
from ga3ce_prep.experiments.named import EXPERIMENTS, at_last_epoch, demo_experiment
from ga3ce_prep.files import file_sha256
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.worlds import SMALL
from ga3ce_prep.train import evaluate
from ga3ce_prep.train.checkpoint import CheckpointError
from ga3ce_prep.train.dataset import store_fingerprint

TINY = World(rooms=3, sessions=3, frames=2, seed=3, width=160, overrides=tuple(SMALL))
TINY_TRANSFER = World(fmt="cad120", preset="transfer", rooms=1, sessions=1, frames=4, seed=3, width=160,
                      overrides=tuple(SMALL))


def tiny(**kw) -> Experiment:
    args = dict(name="tiny", question="does it run?", worlds={"w": TINY},
                arms=(Arm("full"), Arm("no-objects"), Arm("ours")), seeds=(0, 1),
                transfer={"t": TINY_TRANSFER}, recipe={"epochs": 1, "batch_size": 8})
    return Experiment(**{**args, **kw})


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp")
    return out, run_experiment(tiny(), out, progress=False)


def test_results_carry_scores_and_conditions(done):
    out, r = done
    assert json.loads((out / "runs" / "tiny" / "results.json").read_text()) == json.loads(json.dumps(r, default=float))
    # 3 arms x 2 seeds, each scored on its world and on the transfer world
    assert len(r["scores"]) == 12
    assert {(s["arm"], s["seed"], s["scored_on"]) for s in r["scores"]} == {
        (a, k, on) for a in ("full", "no-objects", "ours") for k in (0, 1) for on in ("w", "t")}
    m = r["machine"]
    assert m["vector_unit"] in ("default", "avx2", "avx512") and m["threads"] >= 1 and m["cpu"]
    assert len(r["code"]["commit"] or "x" * 40) == 40
    w = r["worlds"]["w"]
    assert w["protocol"] == "seen rooms" and w["rooms"] == 3 and w["stages"]["objects"]["backend"] == "geometric"
    assert r["transfer"]["t"]["preset"] == "transfer"
    assert r["arms"]["ours"]["design"] == "pointer-frozen" and r["arms"]["full"]["design"] == "ga3ce"
    assert r["arms"]["full"]["config"]["epochs"] == 1 and r["arms"]["full"]["config"]["batch_size"] == 8
    for s in r["scores"]:
        assert 0 < s["mae3d"] < 180 and 0 < s["scored"] <= s["expected"]


def test_a_score_is_the_evaluation_of_its_checkpoint(done):
    out, r = done
    s = next(s for s in r["scores"] if s["arm"] == "ours" and s["seed"] == 1 and s["scored_on"] == "t")
    direct = evaluate(str(out / "t.zarr"), out / "runs" / "tiny" / "w" / "ours" / "seed1" / "best.pt", split="test",
                      cdf_path=None, no_objects=None, compare={})
    assert s["mae3d"] == pytest.approx(direct.methods["model"].mae3d, abs=1e-9)
    assert s["v_prior_mae3d"] == pytest.approx(direct.methods["view_prior"].mae3d, abs=1e-9)
    table = mae_table(r)
    assert table[("w", "t")]["ours"][1] == s["mae3d"]
    assert list(table[("w", "w")]) == ["full", "no-objects", "ours", "v prior"]
    text = format_results(r)
    full = table[("w", "w")]["full"]
    assert f"{np.mean(full):.2f} +- {np.std(full):.2f}" in text and f"{full[0]:.2f} / {full[1]:.2f}" in text
    assert "seen rooms, test split" in text and "machine: " in text


def test_a_rerun_trains_nothing_and_a_changed_recipe_is_refused(done):
    out, r = done
    runs = out / "runs" / "tiny" / "w"
    before = {p: p.stat().st_mtime_ns for p in runs.rglob("best.pt")}
    again = run_experiment(tiny(), out, progress=False)
    assert {p: p.stat().st_mtime_ns for p in runs.rglob("best.pt")} == before
    assert [s["mae3d"] for s in again["scores"]] == [s["mae3d"] for s in r["scores"]]
    with pytest.raises(CheckpointError, match="lr"):
        run_experiment(tiny(arms=(Arm("full", recipe={"lr": 1e-3}),)), out, progress=False)
    # the ours arm's g0 is its no-objects twin, weight for weight
    assert (runs / "ours" / "seed0" / "g0" / "best.pt").is_file()


def test_the_last_epoch_is_scored_on_the_same_runs(done):
    """at_last_epoch scores each run's last.pt in the experiment's own run folders: nothing trains
    again, and the score file is keyed by last.pt's bytes, not best.pt's."""
    out, r = done
    runs = out / "runs" / "tiny"
    before = {p: p.stat().st_mtime_ns for p in runs.rglob("*.pt")}
    last = run_experiment(at_last_epoch(tiny()), out, progress=False)
    assert {p: p.stat().st_mtime_ns for p in runs.rglob("*.pt")} == before
    assert not (out / "runs" / "tiny-last" / "w").exists()
    assert (out / "runs" / "tiny-last" / "results.json").is_file() and last["checkpoint"] == "last"
    s = next(s for s in last["scores"] if s["arm"] == "full" and s["seed"] == 0 and s["scored_on"] == "w")
    run = runs / "w" / "full" / "seed0"
    direct = evaluate(str(out / "w.zarr"), run / "last.pt", split="test", cdf_path=None, no_objects=None, compare={})
    assert s["mae3d"] == pytest.approx(direct.methods["model"].mae3d, abs=1e-9)
    fingerprint = store_fingerprint(open_store(out / "w.zarr"))
    key = hashlib.sha256(f"{file_sha256(run / 'last.pt')}|{fingerprint}|test".encode()).hexdigest()[:16]
    assert json.loads((run / f"scored-test-{key}.json").read_text())["mae3d"] == s["mae3d"]
    assert "last epoch scored" in format_results(last) and "last epoch scored" not in format_results(r)
    with pytest.raises(ConfigError, match="checkpoint"):
        tiny(checkpoint="median")


def test_part_of_an_experiment_runs_by_its_worlds():
    e = tiny(worlds={"w": TINY, "w2": World(seed=9)})
    assert list(e.with_worlds(("w2",)).worlds) == ["w2"] and e.with_worlds(("w2",)).transfer == e.transfer
    with pytest.raises(ConfigError, match="no training worlds"):
        e.with_worlds(("nope",))


def test_declarations_are_checked():
    with pytest.raises(ConfigError, match="unknown rows"):
        tiny(arms=(Arm("no-such-row"),))
    with pytest.raises(ConfigError, match="share a folder"):
        tiny(arms=(Arm("full"), Arm("full", recipe={"lr": 1e-3})))
    d = demo_experiment()
    assert [a.row for a in d.arms] == ["full", "no-objects", "ours"] and d.worlds["calibrated"].sessions == 4
    assert set(EXPERIMENTS) >= {"demo", "paper-tables"}
    assert World.from_json(TINY.to_json()) == TINY
    # an arm's model fields go on top of its row's, a world's frame cap into the recipe
    e = tiny(worlds={"w": TINY, "w2": World(seed=9, pipeline="synthetic-oracle", data="w", train_frames=40)},
             arms=(Arm("ours", model={"pointer_kappa": 100.0}, name="k"),))
    cfg = e.train_config(Path("o"), "w2", e.arms[0], 1)
    assert (cfg.model.method, cfg.model.pointer_kappa, cfg.train_frames, cfg.epochs) == ("pointer-frozen", 100.0, 40, 1)
    assert cfg.out == str(Path("o/runs/tiny/w2/k/seed1")) and cfg.store == str(Path("o/w2.zarr"))
    assert e.data_dirs(Path("o")) == {"w": Path("o/w"), "w2": Path("o/w"), "t": Path("o/t")}
    assert e.train_config(Path("o"), "w", e.arms[0], 0).train_frames is None
    ov = EXPERIMENTS["objects-value-truth"]
    assert ov.data_dirs(Path("o"))["ov-small-truth"] == Path("o/ov-small")
    assert ov.worlds["ov-large-truth"].train_frames == 6000
    assert ov.worlds["ov-small-truth"].pipeline == "synthetic-oracle"


def test_the_cli_lists_and_shows(done):
    out, _ = done
    res = CliRunner().invoke(experiment_cli, ["list"])
    assert res.exit_code == 0 and "paper-tables" in res.output and "60 rooms x 5 sessions x 20 frames" in res.output
    res = CliRunner().invoke(experiment_cli, ["show", os.fspath(out / "runs" / "tiny" / "results.json")])
    assert res.exit_code == 0 and "scored" in res.output and "pointer-frozen (ours)" in res.output


def test_a_dataset_the_old_demo_wrote_is_reused(tmp_path):
    """An out/ folder from before worlds were objects: its demo-params.json names the same world, so
    the dataset is kept (and stamped), never refused or written again; another world's is refused."""
    demo = demo_experiment()
    data = tmp_path / "synthetic"
    data.mkdir()
    (data / "truth.h5").write_text("")
    (data / "demo-params.json").write_text(json.dumps({"fmt": "gfie", "scenes": 48, "sessions_per_room": 4,
                                                       "frames_per_scene": 15, "seed": 0}))
    assert demo.worlds["calibrated"].ensure_data(data) == data
    assert json.loads((data / "world.json").read_text()) == demo.worlds["calibrated"].synth_params()
    (data / "world.json").unlink()
    with pytest.raises(Exception, match="other contents"):
        demo_experiment(seed=1).worlds["calibrated"].ensure_data(data)


def test_results_carry_each_session_and_gains_have_intervals(done):
    from ga3ce_prep.experiments.intervals import gain

    _, r = done
    s = next(s for s in r["scores"] if s["arm"] == "full" and s["scored_on"] == "w")
    assert sum(n for n, _, _ in s["sessions"].values()) == s["scored"]
    assert sum(n * m for n, m, _ in s["sessions"].values()) / s["scored"] == pytest.approx(s["mae3d"], abs=1e-9)
    assert s["curve"]["epochs"] == 1 and s["curve"]["best_epoch"] == 1 and s["curve"]["val_best"] > 0
    near, far = s["target"]["at_object"], s["target"]["elsewhere"]
    assert near[0] + far[0] == s["scored"]
    assert sum(n * m for n, m, _ in (near, far) if n) / s["scored"] == pytest.approx(s["mae3d"], abs=1e-6)
    g = gain(r, ["w"], "full", "no-objects", n_boot=200)
    mae = {a: np.mean([x["mae3d"] for x in r["scores"] if x["arm"] == a and x["scored_on"] == "w"])
           for a in ("full", "no-objects")}
    assert g["gain"] == pytest.approx(1 - mae["full"] / mae["no-objects"], abs=1e-9)
    assert g["low"] <= g["gain"] <= g["high"] and g["seeds"] == [0, 1]


def test_a_gain_and_its_interval_are_the_session_bootstraps():
    from ga3ce_prep.experiments.intervals import gain

    rng = np.random.default_rng(0)

    def score(world, arm, seed, maes):
        return {"world": world, "arm": arm, "seed": seed, "scored_on": world,
                "sessions": {f"s{i}": [10, m, 20.0] for i, m in enumerate(maes)}}

    base = rng.uniform(14, 18, (2, 40))   # two worlds of 40 sessions of 10 frames
    scores = [score(f"w{w}", "b", k, base[w] + rng.normal(0, 0.1, 40)) for w in range(2) for k in range(3)]
    scores += [score(f"w{w}", "a", k, 0.9 * base[w] + rng.normal(0, 0.1, 40)) for w in range(2) for k in range(3)]
    g = gain({"scores": scores}, ["w0", "w1"], "a", "b", n_boot=500)
    assert g["gain"] == pytest.approx(0.10, abs=0.005) and g["low"] < 0.10 < g["high"]
    assert g["high"] - g["low"] < 0.01                     # paired: the sessions' spread cancels
    assert set(g["per_world"]) == {"w0", "w1"} and len(g["per_seed"]) == 3 and g["v_prior"] == 20.0


def test_a_target_is_at_an_object_within_twenty_centimetres():
    from ga3ce_prep.train.evaluate import target_at_object

    objects = np.array([[[0.0, 0, 2], [1, 0, 2]], [[0.0, 0, 2], [9, 9, 9]], [[0.0, 0, 2], [0, 0, 0]]])
    mask = np.array([[1, 1], [1, 0], [0, 0]], bool)
    target = np.array([[1.1, 0, 2], [0.0, 0.25, 2], [0.0, 0, 2]])
    assert target_at_object(target, objects, mask).tolist() == [True, False, False]   # masked objects do not count
    assert not target_at_object(np.full((1, 3), np.nan), objects[:1], mask[:1]).any()


def test_a_gain_splits_by_where_the_target_is():
    from ga3ce_prep.experiments.intervals import target_gains

    def score(arm, seed, near, far):
        return {"world": "w", "arm": arm, "seed": seed, "scored_on": "w",
                "target": {"at_object": [30, near, 20.0], "elsewhere": [10, far, 20.0]}}

    r = {"scores": [score("b", 0, 10.0, 12.0), score("b", 1, 10.0, 12.0), score("a", 0, 8.0, 12.6),
                    score("a", 1, 9.0, 12.6)]}
    split = target_gains(r, ["w"], "a", "b")
    assert split["at_object"] == (pytest.approx(1 - 17 / 20), 30) and split["elsewhere"] == (pytest.approx(-0.05), 10)
    del r["scores"][0]["target"]
    assert target_gains(r, ["w"], "a", "b") == {}
    # no target point in the annotation (GAFA's): no frame at an object, so no split
    r = {"scores": [{**score(a, 0, float("nan"), 12.0), "target": {"at_object": [0, float("nan"), float("nan")],
                                                                    "elsewhere": [40, m, 20.0]}}
                    for a, m in (("a", 11.0), ("b", 12.0))]}
    assert target_gains(r, ["w"], "a", "b") == {}


def test_a_results_file_names_no_machine_paths(tmp_path, monkeypatch):
    """Paths in a results record, keys included, come out relative to the output folder, the
    package or the registry's model cache; others stay as they are."""
    from ga3ce_prep.experiments.experiment import portable

    monkeypatch.setenv("GA3CE_MODELS", str(tmp_path / "models"))
    out = tmp_path / "out"
    record = {"store": str(out / "w.zarr"), "stages": [{"models": {str(tmp_path / "models" / "m-1" / "a.onnx"): "ab"}}],
              "pipeline": str(Path(portable.__code__.co_filename).parents[1] / "pipelines" / "synthetic.yaml"),
              "data": "/elsewhere/x"}
    assert portable(record, out) == {"store": "w.zarr", "stages": [{"models": {"{models cache}/m-1/a.onnx": "ab"}}],
                                     "pipeline": "ga3ce_prep/pipelines/synthetic.yaml", "data": "/elsewhere/x"}
