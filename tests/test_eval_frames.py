"""`eval` scores the dataset's own rows and accounts for every other one: on a synthetic GFIE world
whose test frames include head boxes without depth (scored through the head fallbacks) and a frame
the pipeline drops; GAFA's window rule on hand-made frame numbers; GAFA's validation rule; GAFA's
Table 3 layout on a synthetic GAFA-format store."""
import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.datasets.gafa import SESSION_ORDER, TRAIN_SESSIONS, gafa_val_starts, window_starts
from ga3ce_prep.frames import FrameRef
from ga3ce_prep.model import ModelConfig
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.store import open_store
from ga3ce_prep.synthetic import generate
from ga3ce_prep.synthetic.config import load_config
from ga3ce_prep.testing.worlds import SMALL, SMALL_WORLD
from ga3ce_prep.train import TrainConfig, evaluate, format_eval_table, train
from ga3ce_prep.train.ablate import BY_NAME, format_ablation_table
from ga3ce_prep.train.checkpoint import load_checkpoint
from ga3ce_prep.train.frameset import gafa_windows
from ga3ce_prep.train.profiles import DatasetProfile

TINY = ModelConfig(num_encoder_layers=1, num_decoder_layers=1, dim_feedforward=64, head_hidden=64)


def _train(store, out):
    return train(TrainConfig(store=str(store), out=str(out), epochs=1, progress=False, model=TINY)) / "best.pt"


@pytest.fixture(scope="module")
def holed(tmp_path_factory):
    """A 160x120 GFIE-format world (3 scenes x 4 frames) where most frames have no depth in the
    head box, one test frame's image removed (the input stage drops it), its store and a checkpoint."""
    root = tmp_path_factory.mktemp("holed")
    world = root / "w"
    generate("gfie", world, progress=False, config=load_config("gfie", overrides={"depth": {"head_hole_prob": 0.8}}),
             **SMALL_WORLD)
    (world / "rgb" / "test" / "scene1" / "0002.jpg").unlink()
    run_pipeline("synthetic", world, root / "s.zarr", overrides=SMALL, progress=False)
    return world, root / "s.zarr", _train(root / "s.zarr", root / "run")


def test_eval_scores_the_datasets_test_rows_through_the_fallback(holed, tmp_path):
    world, store, ckpt = holed
    rows = (world / "test_annotation.txt").read_text().strip().splitlines()[1:]
    r = evaluate(store, ckpt, split="test", cdf_path=None, json_path=tmp_path / "e.json")
    fr = r.frames
    assert fr.protocol == "all" and fr.expected == len(rows) == 4   # every row of the test file
    assert fr.scored == r.n_frames == 3
    assert fr.unscored == {"dropped by the input stage (FrameError)": ["test/scene1/0002"]}
    assert r.head_sources == {"measured": 1, "pose_depth": 2}         # pinned: 2 scored through the fallback
    assert r.head_fallback_frames == 2
    assert json.loads((tmp_path / "e.json").read_text())["frames"]["unscored"] == fr.unscored
    table = format_eval_table(r)
    assert "scored 3 of 4 test frames: every frame of the split" in table
    assert "1 not scored: dropped by the input stage (FrameError) (e.g. test/scene1/0002)" in table
    assert "head position of the scored frames: measured 1, pose_depth 2" in table
    res = CliRunner().invoke(cli, ["eval", "--store", str(store), "--checkpoint", str(ckpt), "--cdf", "none"])
    assert res.exit_code == 0, res.output
    assert "scored 3 of 4 test frames" in res.output


def test_eval_names_frames_the_run_never_read_and_works_from_a_moved_dataset(holed, tmp_path):
    world, _, ckpt = holed
    n = len(list(open_dataset("gfie", world).frames()))
    moved = tmp_path / "moved"
    shutil.copytree(world, moved)
    run_pipeline("synthetic", moved, tmp_path / "lim.zarr", overrides=SMALL, limit=n - 2, progress=False)
    shutil.rmtree(moved)
    with pytest.raises(Exception, match="windows need the dataset's frames"):
        evaluate(tmp_path / "lim.zarr", ckpt, force=True, cdf_path=None, frames="windows")
    r = evaluate(tmp_path / "lim.zarr", ckpt, force=True, cdf_path=None)   # the store alone: its frames
    assert (r.frames.expected, r.frames.scored) == (2, 2)
    assert r.frames.source.startswith("the store's frames")
    r = evaluate(tmp_path / "lim.zarr", ckpt, force=True, cdf_path=None, data=world)
    fr = r.frames
    order = [f.id for f in open_dataset("gfie", world).frames() if f.split == "test"]
    assert order[-2:] == ["test/scene1/0002", "test/scene1/0003"]          # the adapter's last two rows
    assert (fr.expected, fr.scored) == (4, 2)
    assert fr.unscored == {f"not read by the run (--limit {n - 2})": order[-2:]}


def test_gafa_window_rule_on_frame_numbers_with_gaps():
    # raw frame numbers 0-10, 12-24 (11 is missing): windows start every 7 positions (0, 7, 14) and
    # are kept only over 7 consecutive numbers; the window at 7 spans the gap (7..10, 12..14)
    index = np.r_[0:11, 12:25]
    assert window_starts(index, 7).tolist() == [0, 14]
    # interval 1 (training, GAFA's val rule): every window not spanning the gap, but not the one
    # ending on the last frame (GAFA's range(0, n - 7)): 17 would be 18..24
    assert window_starts(index, 1).tolist() == [0, 1, 2, 3, 4, 11, 12, 13, 14, 15, 16]
    assert window_starts(np.arange(6), 1).tolist() == []
    # two sequences, each given in reverse order; front/back per window from its first frame's ground truth
    frames = []
    for seq, numbers in (("a", np.arange(15)), ("b", np.r_[0:3, 4:17])):
        for k in numbers.tolist():
            z = -1.0 if k in (0, 8) else 1.0
            frames.append(FrameRef(id=f"{seq}/{k}", split="test", scene=seq, image_path="x", K=np.eye(3),
                                   image_size=(1, 1), head_box=np.zeros(4, np.float32), sequence=seq, index=k,
                                   gaze=np.array([0, 0, z], np.float32)))
    chosen, front = gafa_windows(sorted(frames, key=lambda f: (f.sequence, -f.index)))
    assert [f.id for f in chosen] == [f"a/{k}" for k in range(14)] + [f"b/{k}" for k in range(8, 15)]
    assert front.tolist() == [True] * 7 + [False] * 7 + [True] * 7      # a/0 front, a/7 back, b/8 front


def test_gafa_validation_rule_is_the_seeded_tail_of_the_shuffled_training_windows():
    numbers = {f"{s}/Camera1_0": np.arange(20) for s in TRAIN_SESSIONS}      # 13 windows (interval 1) each
    numbers["lab/1013_1/Camera2_0"] = np.array([0, 1, 2, 3, 5, 6, 7, 8, 9, 10, 11, 12])  # 3 windows after the gap
    out = gafa_val_starts(numbers, seed=0)
    order = [TRAIN_SESSIONS[k] for k in np.random.default_rng(0).permutation(len(TRAIN_SESSIONS))]
    windows = 11 * 13 + 3
    n_val = windows - int(windows * 0.9)                                    # 15 windows: GAFA's int()
    cams = [c for s in order for c in sorted(numbers) if c.startswith(s + "/")]
    counts = [3 if c == "lab/1013_1/Camera2_0" else 13 for c in cams]
    tail = np.cumsum(counts[::-1])
    k = int(np.searchsorted(tail, n_val))                                   # cameras from the end holding the cut
    cut_cam = cams[len(cams) - 1 - k]
    into = counts[len(cams) - 1 - k] - (n_val - (tail[k - 1] if k else 0))  # windows of it that stay train
    expect = window_starts(numbers[cut_cam], 1)[into]
    assert out[cut_cam] == expect
    for c in cams[len(cams) - k:]:
        assert out[c] == 0                                                  # all val
    for c in cams[:len(cams) - 1 - k]:
        assert out[c] == len(numbers[c])                                    # all train
    assert gafa_val_starts(numbers, seed=0) == out                          # seeded
    assert gafa_val_starts(numbers, seed=1) != out


@pytest.fixture(scope="module")
def gafa_store(tmp_path_factory):
    """14 GAFA sessions (SESSION_ORDER's first 14: test lab, living room, kitchen, library and both
    courtyard sessions) x 15 raw frames per camera at 160 px, oracle stages."""
    root = tmp_path_factory.mktemp("gafa3")
    world = root / "w"
    generate("gafa", world, scenes=14, frames_per_scene=15, seed=3, width=160, progress=False)
    stages = {"depth": {"backend": "oracle"}, "objects": {"backend": "oracle"}, "head": {"backend": "depth"},
              "pose": {"backend": "oracle"}, "view": {"backend": "oracle"}}
    run_pipeline({"name": "gafa-oracle", "dataset": {"format": "gafa"}, "stages": stages}, world, root / "s.zarr",
                 progress=False)
    return world, root / "s.zarr", _train(root / "s.zarr", root / "run")


def test_gafa_eval_prints_table_3_per_scene_over_gafa_windows(gafa_store):
    world, store, ckpt = gafa_store
    assert {"courtyard/002", "courtyard/003", "lab/1013_2"} <= set(SESSION_ORDER[:14])
    frames = [f for f in open_dataset("gafa", world).frames() if f.split == "test"]
    chosen, front = gafa_windows(frames)
    r = evaluate(store, ckpt, cdf_path=None)
    fr = r.frames
    assert fr.protocol == "windows"
    assert fr.expected == len(chosen) == 14 * len({f.sequence for f in chosen}) < fr.split_rows == len(frames)
    assert fr.scored == r.n_frames == len(chosen) - 5                  # pinned: 5 with an empty head box
    assert list(fr.unscored) == ["dropped by the input stage (FrameError)"]
    assert r.scene_columns == ["Office", "Living room", "Kitchen", "Library", "Courtyard"]
    st = open_store(store)
    scored = set(st.frames["id"][np.isin(st.frames["id"], [f.id for f in chosen])].tolist())
    per = r.methods["model"].per_scene
    court = [f.id for f in chosen if f.scene.startswith("courtyard/") and f.id in scored]
    assert per["Courtyard"].n == len(court)
    assert {i.rsplit("/", 2)[0] for i in court} == {"courtyard/002", "courtyard/003"}    # merged by frames
    assert per["Office"].n == sum(f.scene == "lab/1013_2" and f.id in scored for f in chosen)
    assert sum(p.n for p in per.values()) == r.n_frames
    assert r.methods["model"].front.n == int(front[[f.id in scored for f in chosen]].sum())  # per window
    # a column's 3D is the mean over its frames: the merged courtyard, by frames
    sel = np.isin(st.frames["id"], court)
    v, g = st.frames["view"][sel], st.frames["gaze"][sel]
    e = np.degrees(np.arccos(np.clip(np.sum(v * g, 1) / np.linalg.norm(v, axis=1) / np.linalg.norm(g, axis=1), -1, 1)))
    assert r.methods["view_prior"].per_scene["Courtyard"].mae3d == pytest.approx(e.mean(), abs=1e-3)
    table = format_eval_table(r)
    assert "GAFA's 7-frame windows (raw-consecutive frames, interval 7)" in table
    header = next(line for line in table.splitlines() if "Office" in line)
    assert header.split() == ["Office", "Living", "room", "Kitchen", "Library", "Courtyard", "All"]
    paper = next(line for line in table.splitlines() if line.startswith("GA3CE, the paper's figure"))
    assert paper.split()[-3:] == ["19.9", "/", "-"] and paper.count("-   /   -") == 5   # the unknown cells stay empty
    every = evaluate(store, ckpt, cdf_path=None, frames="all")
    assert every.frames.expected == len(frames)
    assert every.n_frames == every.frames.scored > r.n_frames
    assert "every frame of the split, NOT GAFA's protocol" in format_eval_table(every)
    assert every.paper_rows == {}


def test_recipe_batch_size_per_dataset_and_gafa_ablation_labels(gafa_store):
    _, _, ckpt = gafa_store
    assert json.loads((ckpt.parent / "config.json").read_text())["batch_size_resolved"] == 64   # GAFA's recipe
    assert load_checkpoint(ckpt)["config"]["batch_size"] is None                              # unset: the profile's
    assert [DatasetProfile.for_dataset(d).batch_size for d in ("gfie", "cad120", "gafa", "toy")] == [32, 32, 64, 32]
    rows = [{"name": a, "label": BY_NAME[a].label, "table4": BY_NAME[a].table4, "table5": BY_NAME[a].table5,
             "mae3d": m, "mae3d_std": None, "ratio": m / 20.0, "paper_gfie": BY_NAME[a].paper_gfie,
             "paper_gafa": BY_NAME[a].paper_gafa, "paper_ratio_gfie": None,
             "paper_ratio_gafa": BY_NAME[a].paper_gafa / 22.9} for a, m in (("appearance", 20.0), ("full", 18.0))]
    summary = {"store": "s", "split": "test", "v_prior_mae3d": 20.0, "epochs": 1, "seeds": [0], "rows": rows,
               "paper_column": "gafa", "appearance_is_v": False, "full_best": True}
    t = format_ablation_table(summary)
    assert "appearance only: v (ours)" in t and "appearance only (v)" not in t
    assert "GAFA's own gaze module (22.9), not a view prior" in t
    assert "appearance only (v)" in format_ablation_table({**summary, "paper_column": "gfie", "appearance_is_v": True})


def test_gafa_adapter_marks_the_val_tail_and_keeps_the_sessions_option(gafa_store):
    world = gafa_store[0]
    frames = list(open_dataset("gafa", world).frames())
    train = [f for f in frames if f.split != "test"]
    numbers = {s: np.array([f.index for f in train if f.sequence == s])
               for s in dict.fromkeys(f.sequence for f in train)}
    starts = gafa_val_starts(numbers, seed=0)
    position = {f.id: int(np.searchsorted(numbers[f.sequence], f.index)) for f in train}
    assert [f.split for f in train] == ["val" if position[f.id] >= starts[f.sequence] else "train" for f in train]
    n_val = sum(f.split == "val" for f in train)
    assert 0 < n_val < 0.2 * len(train)                                    # a tail, about 10% of the windows
    assert sum(0 < starts[s] < len(numbers[s]) for s in numbers) <= 1       # the cut falls inside one sequence at most
    other = {f.id: f.split for f in open_dataset("gafa", world, val_seed=1).frames()}
    assert other != {f.id: f.split for f in frames}                         # another seed, another tail
    by_session = {f.scene: f.split for f in open_dataset("gafa", world, val="sessions").frames() if f.split == "val"}
    assert set(by_session) == {"kitchen/1015_4", "courtyard/005"}
