"""Bad inputs through the command line, as a careless or hostile user makes them from the synthetic
world: wrong units and types are refused (dataset-wide faults before any work, one frame's as its
failure record), and every refusal is one `error:` line naming the file, the field and the fix,
with nothing half-written left behind (docs/datasets.md, "What is checked")."""
import csv
import os
import pickle
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from ga3ce_prep.bundled import pipeline_text
from ga3ce_prep.cli import main
from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.store import open_store
from ga3ce_prep.synthetic import generate
from ga3ce_prep.synthetic.truth import TruthReader
from ga3ce_prep.testing.worlds import SMALL, SMALL_WORLD, as_folder, truth_file

RUN = [*SMALL, "run.shard_size=12"]
GAFA = ["dataset.format=gafa", "stages.depth.backend=oracle", "stages.depth.params={truth: '{data}/truth.h5'}"]


@pytest.fixture
def ga3ce(monkeypatch, capsys):
    """`ga3ce-prep ARGS` through `ga3ce_prep.cli.main` (the entry point's error handling) in this
    process: (exit code, stdout, stderr)."""
    monkeypatch.delenv("GA3CE_DEBUG", raising=False)

    def call(*args) -> tuple[int, str, str]:
        monkeypatch.setattr(sys, "argv", ["ga3ce-prep", *map(str, args)])
        code = 0
        try:
            main()
        except SystemExit as e:
            code = e.code
        out = capsys.readouterr()
        return code, out.out, out.err

    return call


def _run(ga3ce, data, out, *sets, pipeline="synthetic", extra=()):
    args = ["run", "-p", pipeline, "-d", data, "-o", out, "-q", *extra]
    for s in (*RUN, *sets):
        args += ["--set", s]
    return ga3ce(*args)


def refused(result, out: Path | None, *fragments: str, code: int = 2) -> str:
    """Assert one `error:` line on stderr holding every fragment, the exit code (2: ga3ce-prep's own
    errors), and (out) neither the store nor its work directory written. Returns the line."""
    got, stdout, stderr = result
    assert got == code, (got, stdout, stderr)
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    if out is not None:
        assert not out.exists() and not Path(f"{out}.work").exists()
    return lines[0]


def _copy(src: Path, tmp_path: Path, name: str = "data") -> Path:
    dst = tmp_path / name
    shutil.copytree(src, dst)
    return dst


def _edit_csv(path: Path, edit) -> None:
    """Rewrite a CSV: edit(header, rows) changes the rows (lists of cells) in place."""
    rows = list(csv.reader(open(path, newline="")))
    edit(rows[0], rows[1:])
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)


def _bomb(path: Path, side: int) -> None:
    """A PNG header declaring side x side RGB pixels, with no pixel data (a decompression bomb)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b""))
                     + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def reference(synth_world, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "ref.zarr"
    run_pipeline("synthetic", synth_world, out, overrides=RUN, progress=False)
    return open_store(out)


@pytest.fixture(scope="module")
def cad_world(tmp_path_factory):
    root = tmp_path_factory.mktemp("cad") / "cad120"
    generate("cad120", root, progress=False, **SMALL_WORLD)
    return root


# ---------------------------------------------------------------- wrong units and types

@pytest.mark.parametrize("factor, unit", [(100, "cm"), (1000, "mm")])
def test_gfie_depth_units_are_inferred_recorded_and_stored_as_metres(synth_world, reference, tmp_path, ga3ce,
                                                                      factor, unit):
    data = _copy(synth_world, tmp_path)
    for p in (data / "depth").rglob("*.npy"):
        np.save(p, np.load(p) * factor)
    assert open_dataset("gfie", data).provenance()["units"] == {
        "depth": unit, "eye_gaze_xyz": "m", "boxes": "x1, y1, x2, y2 pixels", "decided_by": "the data (units: auto)"}
    code, _, err = _run(ga3ce, data, tmp_path / "s.zarr")
    assert code == 0, err
    s = open_store(tmp_path / "s.zarr")
    assert s.attrs["dataset"]["units"]["depth"] == unit                  # recorded in the store's provenance
    np.testing.assert_array_equal(s.frames["id"], reference.frames["id"])
    np.testing.assert_allclose(s.frames["head_pos"], reference.frames["head_pos"], atol=1e-4)  # 3 m, not 300 or 3000


def test_depth_in_another_unit_than_stated_is_refused(synth_world, tmp_path, ga3ce):
    data = _copy(synth_world, tmp_path)
    for p in (data / "depth").rglob("*.npy"):
        np.save(p, np.load(p) * 100)  # centimetres
    refused(_run(ga3ce, data, tmp_path / "s.zarr", "dataset.options.units=m"), tmp_path / "s.zarr",
            "depth/train/scene1/0000.npy", "median depth", "(read as units m) is outside the plausible 0.1-100 m",
            "read as cm (", "set dataset.options.units (now m)")
    for p in (data / "depth").rglob("*.npy"):
        np.save(p, np.load(p) * 2)  # 1/200 m: a median of about 700, 7 m as cm, 0.7 m as mm
    refused(_run(ga3ce, data, tmp_path / "s.zarr"), tmp_path / "s.zarr",
            "GFIE depth", "0000.npy", "fits cm and mm alike", "set dataset.options.units")


def test_8bit_depth_png_is_refused(cad_world, tmp_path, ga3ce):
    data = _copy(cad_world, tmp_path)
    for p in (data / "depth").rglob("*.png"):
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), (d // 20).clip(0, 255).astype(np.uint8))  # a visualisation, read as mm: 0.1 m heads
    refused(_run(ga3ce, data, tmp_path / "s.zarr", "dataset.format=cad120"), tmp_path / "s.zarr",
            "depth/D1S1A001/Depth_1.png is 8-bit (uint8", "needs 16 bits (uint16 millimetres)",
            "export the raw depth")


def test_pose_file_in_millimetres_is_refused_then_read_with_its_units(synth_world, tmp_path, ga3ce):
    pose_mm = truth_file(synth_world, tmp_path / "pose_mm.npz", "pose", 1000.0)
    pose = [f"stages.pose={{backend: precomputed, params: {{file: '{pose_mm}'}}}}"]
    refused(_run(ga3ce, synth_world, tmp_path / "s.zarr", *pose), tmp_path / "s.zarr",
            "pose of frame test/scene1/0000 in", "pose_mm.npz", "median person size", "(read as units m)",
            "outside the plausible 0.1-3 m", "read as mm (", "set stages.pose.params.units (now m)")
    code, _, err = _run(ga3ce, synth_world, tmp_path / "s.zarr", *pose, "stages.pose.params.units=mm")
    assert code == 0, err
    s = open_store(tmp_path / "s.zarr")
    t = TruthReader(synth_world / "truth.h5")
    truth = t.array("pose")[[t.index(f) for f in s.frames["id"]]]
    np.testing.assert_allclose(s.frames["pose"], truth, atol=1e-5)
    assert s.attrs["stages"]["pose"]["params"]["units"] == "mm"


def test_gafa_head_positions_in_millimetres_are_refused(synth_gafa_world, tmp_path, ga3ce):
    data = _copy(synth_gafa_world, tmp_path)
    pkl = sorted(data.rglob("*.pkl"))[0]
    d = pickle.loads(pkl.read_bytes())
    d["head"]["position"] = np.asarray(d["head"]["position"]) * 1000
    pkl.write_bytes(pickle.dumps(d))
    refused(_run(ga3ce, data, tmp_path / "s.zarr", *GAFA), tmp_path / "s.zarr",
            f"{pkl} head['position']: median head distance", "outside the plausible 0.1-100 m", " mm (2.8 m)",
            "set the pickle's positions to metres (GAFA's unit)")


@pytest.mark.parametrize("k, why", [([np.nan] * 4, "are not finite"), ([0.0, 0.0, 80.0, 60.0], "have fx or fy <= 0")])
def test_intrinsics_nan_or_zero_stop_before_any_work(synth_world, tmp_path, ga3ce, k, why):
    data = _copy(synth_world, tmp_path)
    np.save(data / "CameraKinect.npy", np.array(k))
    refused(_run(ga3ce, data, tmp_path / "s.zarr"), tmp_path / "s.zarr",
            f"{data / 'CameraKinect.npy'}: intrinsics fx", why, "write the camera's calibration in pixels (fx, fy > 0)")


def test_boxes_in_another_convention_stop_before_any_work(synth_world, cad_world, tmp_path, ga3ce):
    gfie = _copy(synth_world, tmp_path, "gfie")

    def to_xywh(h, rows):
        for r in rows:
            for lo, hi in (("h_x_min", "h_x_max"), ("h_y_min", "h_y_max")):
                r[h.index(hi)] = str(float(r[h.index(hi)]) - float(r[h.index(lo)]))

    _edit_csv(gfie / "train_annotation.txt", to_xywh)
    refused(_run(ga3ce, gfie, tmp_path / "s.zarr"), tmp_path / "s.zarr",
            "train_annotation.txt: 4 of 4 head boxes (h_x_min, h_y_min, h_x_max, h_y_max) are inverted or empty",
            "(line 2: the box is inverted (x2", "x2 = x + width, y2 = y + height")
    cad = _copy(cad_world, tmp_path, "cad")

    def to_pixels(h, rows):
        for r in rows:
            for c, size in (("x_initial", 160), ("y_initial", 120), ("w", 160), ("h", 120)):
                r[h.index(c)] = str(float(r[h.index(c)]) * size)

    _edit_csv(cad / "annotation.txt", to_pixels)
    refused(_run(ga3ce, cad, tmp_path / "s.zarr", "dataset.format=cad120"), tmp_path / "s.zarr",
            "annotation.txt: the head boxes (x_initial, y_initial, w, h) reach", "they look like pixels",
            "divide by the image's width and height")


def test_one_frames_faults_are_its_failure_records_and_the_others_are_intact(synth_world, reference, tmp_path, ga3ce):
    data = _copy(synth_world, tmp_path)
    dep = data / "depth" / "valid" / "scene1" / "0001.npy"
    np.save(dep, np.load(dep) * 100)                                      # one map in centimetres
    lines = {}

    def break_boxes(h, rows):
        for r in rows:
            n = int(r[h.index("frame_id")])
            if n == 1:                                                    # inverted
                lo, hi = h.index("h_x_min"), h.index("h_x_max")
                r[lo], r[hi] = r[hi], r[lo]
            elif n == 2:                                                  # empty
                r[h.index("h_y_max")] = r[h.index("h_y_min")]
        lines.update({int(r[h.index("frame_id")]): k + 2 for k, r in enumerate(rows)})

    _edit_csv(data / "train_annotation.txt", break_boxes)
    _bomb(data / "rgb" / "test" / "scene1" / "0000.jpg", 15000)           # Pillow would only warn
    _bomb(data / "rgb" / "test" / "scene1" / "0003.jpg", 30000)           # Pillow refuses
    code, out, err = _run(ga3ce, data, tmp_path / "s.zarr")
    assert code == 0, err
    assert "7 kept of 12" in out
    s = open_store(tmp_path / "s.zarr")
    f = s.failures
    got = {fid: (st, msg) for fid, st, msg in zip(f["frame_id"], f["stage"], f["message"])}
    ann = data / "train_annotation.txt"
    expect = {
        "valid/scene1/0001": ("depth", [f"depth {dep}: median depth", "(read as units m)", "read as cm (",
                                        "set the dataset's depth units (dataset.options) or re-export this file"]),
        "train/scene1/0001": ("input", ["head box of frame train/scene1/0001 is inverted (x2",
                                        f"fix {ann}:{lines[1]}"]),
        "train/scene1/0002": ("input", ["head box of frame train/scene1/0002 is empty (zero height",
                                        f"fix {ann}:{lines[2]}"]),
        "test/scene1/0000": ("input", ["test/scene1/0000.jpg: its header declares", "replace it"]),
        "test/scene1/0003": ("input", ["test/scene1/0003.jpg: its header declares", "replace it"]),
    }
    assert sorted(got) == sorted(expect)
    for fid, (stage, fragments) in expect.items():
        assert got[fid][0] == stage, got[fid]
        for frag in fragments:
            assert frag in got[fid][1], (frag, got[fid][1])
    keep = np.isin(reference.frames["id"], s.frames["id"])
    for name in ("head_pos", "pose", "view", "obj_count", "gaze"):
        np.testing.assert_array_equal(s.frames[name], reference.frames[name][keep], err_msg=name)


def test_non_finite_poses_are_failure_records_not_stored_values(synth_world, tmp_path, ga3ce):
    path = truth_file(synth_world, tmp_path / "pose.npz", "pose")
    z = dict(np.load(path))
    row = {fid: i for i, fid in enumerate(z["frame_id"])}
    z["pose"][row["train/scene1/0000"]] = np.nan                          # no joint at all
    z["pose"][row["train/scene1/0001"], 3] = np.inf
    z["pose"][row["train/scene1/0002"], 4] = np.nan                       # one joint not found: fine
    np.savez(path, **z)
    code, out, err = _run(ga3ce, synth_world, tmp_path / "s.zarr",
                          f"stages.pose={{backend: precomputed, params: {{file: '{path}'}}}}")
    assert code == 0, err
    s = open_store(tmp_path / "s.zarr")
    f = s.failures
    got = {fid: (st, msg, act) for fid, st, msg, act in zip(f["frame_id"], f["stage"], f["message"], f["action"])}
    assert set(got) == {"train/scene1/0000", "train/scene1/0001"}
    assert got["train/scene1/0000"] == ("pose", "the pose backend returned no finite joint (90 of 90): not stored "
                                        "as a pose; a backend raises FrameError when it finds none", "degraded")
    assert (got["train/scene1/0001"][0] == "pose"
            and "has infinite values; write NaN for a joint" in got["train/scene1/0001"][1])
    i = list(s.frames["id"]).index("train/scene1/0002")
    assert np.isnan(s.frames["pose"][i, 4]).all() and np.isfinite(np.delete(s.frames["pose"][i], 4, 0)).all()


def test_a_missing_depth_file_is_named_not_blamed_on_a_depth_estimator(synth_world, tmp_path, ga3ce):
    data = as_folder(synth_world, tmp_path / "rec")
    (data / "depth" / "train_scene1_0002.npy").unlink()
    code, out, err = _run(ga3ce, data, tmp_path / "s.zarr", "stages.pose.params.file='{data}/pose.npz'",
                          "stages.view.params.file='{data}/view.npz'", pipeline="folder")
    assert code == 0, err
    f = open_store(tmp_path / "s.zarr").failures
    assert list(zip(f["frame_id"], f["stage"], f["message"])) == [
        ("train_scene1_0002", "depth", f"depth file not found: {data / 'depth' / 'train_scene1_0002.npy'}")]


# ---------------------------------------------------------------- one clear line

@pytest.mark.parametrize("kind", ["list", "strings"])
def test_gafa_pickle_of_the_wrong_type_is_one_line(synth_gafa_world, tmp_path, ga3ce, kind):
    data = _copy(synth_gafa_world, tmp_path)
    pkl = sorted(data.rglob("*.pkl"))[0]
    d = pickle.loads(pkl.read_bytes())
    if kind == "list":
        d = [1, 2, 3]
        frags = [f"{pkl}: holds a list, not a dict", "a GAFA camera pickle is a dict with keys ['keypoints2d'"]
    else:
        d["keypoints2d"] = np.full(np.shape(d["keypoints2d"]), "a", dtype=object).tolist()
        frags = [f"{pkl}: keypoints2d does not hold numbers", "expected a float array (N, 25, >=2) pixels"]
    pkl.write_bytes(pickle.dumps(d))
    refused(_run(ga3ce, data, tmp_path / "s.zarr", *GAFA), tmp_path / "s.zarr", *frags)


@pytest.mark.parametrize("option, fragments", [
    ("units=km", ["dataset.options.units: 'km' is not one of auto, m, cm, mm",
                  "fix it in the pipeline's dataset.options"]),
    ("splits=train", ["dataset.options.splits: 'train' is not a list of train, valid, test"]),
    ("unit=mm", ["dataset.options.unit: the gfie adapter has no such option; its options: units, splits"]),
])
def test_invalid_dataset_options_are_one_line(synth_world, tmp_path, ga3ce, option, fragments):
    refused(_run(ga3ce, synth_world, tmp_path / "s.zarr", f"dataset.options.{option}"), tmp_path / "s.zarr", *fragments)


def test_annotation_files_refused_for_what_they_are(synth_world, reference, tmp_path, ga3ce):
    data = _copy(synth_world, tmp_path)
    ann = data / "train_annotation.txt"
    clean = ann.read_bytes()
    ann.write_bytes(b"\xef\xbb\xbf" + clean)                             # a UTF-8 BOM: read as the header it is
    code, _, err = _run(ga3ce, data, tmp_path / "bom.zarr")
    assert code == 0, err
    np.testing.assert_array_equal(open_store(tmp_path / "bom.zarr").frames["id"], reference.frames["id"])
    text = clean.decode().splitlines()
    ann.write_text("\n".join([text[0], text[1], text[2], text[1], *text[3:]]) + "\n")  # a duplicate row
    refused(_run(ga3ce, data, tmp_path / "s.zarr"), tmp_path / "s.zarr",
            f"{ann}: lines 2 and 4 both annotate frame train/scene1/0000; remove the duplicate row")
    for split in ("train", "valid", "test"):                              # only headers (one alone: an empty split)
        path = data / f"{split}_annotation.txt"
        path.write_text(path.read_text().splitlines()[0] + "\n")
    refused(_run(ga3ce, data, tmp_path / "s.zarr"), tmp_path / "s.zarr",
            f"{ann}, {data / 'valid_annotation.txt'}, {data / 'test_annotation.txt'}: a header and no rows: the "
            "dataset annotates no frame; write the rows")


def test_limit_zero_is_one_line(synth_world, tmp_path, ga3ce):
    refused(_run(ga3ce, synth_world, tmp_path / "s.zarr", extra=["--limit", "0"]), tmp_path / "s.zarr",
            "--limit 0: the number of frames to process must be at least 1", "leave --limit out")


def test_a_damaged_cache_entry_is_recomputed_in_the_same_rerun(synth_world, reference, tmp_path, ga3ce):
    out = tmp_path / "s.zarr"
    assert _run(ga3ce, synth_world, out)[0] == 0
    shutil.rmtree(out)
    (entry,) = (tmp_path / "s.zarr.work" / "cache" / "input").rglob("*.npz")
    z = dict(np.load(entry))
    del z["ok"]
    np.savez(entry, **z)                                                 # readable, but not an entry
    assert _run(ga3ce, synth_world, out)[0] == 0                         # removed and computed again
    assert "ok" in np.load(entry).files
    for name in ("id", "head_pos", "pose", "view", "obj_count"):
        np.testing.assert_array_equal(open_store(out).frames[name], reference.frames[name], err_msg=name)


def _store_and_run(synth_world, tmp_path):
    """A store of the synthetic world (tmp_path/s.zarr) and a one-epoch tiny model trained on it."""
    from ga3ce_prep.model import ModelConfig
    from ga3ce_prep.train import TrainConfig, train

    store = tmp_path / "s.zarr"
    run_pipeline("synthetic", synth_world, store, overrides=RUN, progress=False)
    model = ModelConfig(num_encoder_layers=1, num_decoder_layers=1, dim_feedforward=64, head_hidden=64)
    run = train(TrainConfig(store=str(store), out=str(tmp_path / "run"), epochs=1, batch_size=8, warmup_epochs=0,
                            progress=False, model=model))
    return store, run


def test_eval_refuses_a_foreign_checkpoint_and_bad_splits(synth_world, tmp_path, ga3ce):
    store, run = _store_and_run(synth_world, tmp_path)
    ckpt = torch.load(run / "best.pt", weights_only=True)
    ckpt["config"]["model"].update(joint_width=8, view_width=136)       # another configuration's d_model split
    torch.save(ckpt, tmp_path / "other.pt")
    refused(ga3ce("eval", "--store", store, "--checkpoint", tmp_path / "other.pt", "--cdf", "none"), None,
            f"{tmp_path / 'other.pt'}: the weights are not those of its config.model (weight ",
            "the configuration needs", "they come from another model configuration",
            "use the best.pt or last.pt its run folder wrote")
    refused(ga3ce("eval", "--store", store, "--checkpoint", run / "best.pt", "--split", "tset"), None,
            f"--split tset: store {store} has no split 'tset'; its splits: train, val, test")
    small = tmp_path / "train_only.zarr"
    assert _run(ga3ce, synth_world, small, extra=["--limit", "4"])[0] == 0  # the train scene only
    refused(ga3ce("eval", "--store", small, "--checkpoint", run / "best.pt", "--force"), None,
            f"--split test: store {small} has no test frame with a view prior and ground-truth gaze")
    assert not list(tmp_path.rglob("eval_*"))


def test_relative_paths_are_recorded_absolute(synth_world, tmp_path, ga3ce, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shutil.copytree(synth_world, "data")
    Path("p.yaml").write_text(pipeline_text("synthetic"))
    code, _, err = _run(ga3ce, "data", "s.zarr", "stages.view.params.truth=data/truth.h5", pipeline="p.yaml")
    assert code == 0, err
    a = open_store(tmp_path / "s.zarr").attrs
    assert a["pipeline"]["file"] == str(tmp_path / "p.yaml")
    assert a["dataset"]["root"] == str(tmp_path / "data")
    assert a["pipeline"]["config"]["stages"]["view"]["params"]["truth"] == str(tmp_path / "data" / "truth.h5")
    assert a["stages"]["view"]["params"]["truth"] == str(tmp_path / "data" / "truth.h5")


def test_an_unexpected_error_is_one_line_that_says_it_is_a_bug(ga3ce, monkeypatch, tmp_path):
    import ga3ce_prep.pipeline.run as run_module

    def boom(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(run_module, "run_pipeline", boom)
    refused(ga3ce("run", "-p", "synthetic", "-d", tmp_path, "-o", tmp_path / "s.zarr"), tmp_path / "s.zarr",
            "error: unexpected RuntimeError: boom (at test_bad_inputs.py:", "a bug in ga3ce-prep",
            "rerun with GA3CE_DEBUG=1 for the traceback", code=1)


def test_the_installed_entry_point_prints_one_line_and_exits_2(synth_gafa_world, tmp_path):
    data = _copy(synth_gafa_world, tmp_path)
    pkl = sorted(data.rglob("*.pkl"))[0]
    pkl.write_bytes(pickle.dumps("not a dict"))
    cmd = [sys.executable, "-m", "ga3ce_prep.cli", "run", "-p", "synthetic", "-d", str(data), "-o",
           str(tmp_path / "s.zarr"), "-q"]
    for s in (*RUN, *GAFA):
        cmd += ["--set", s]
    env = {k: v for k, v in os.environ.items() if k != "GA3CE_DEBUG"}
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    refused((p.returncode, p.stdout, p.stderr), tmp_path / "s.zarr", f"{pkl}: holds a str, not a dict")


# ---------------------------------------------------------------- a damaged store, whoever reads it

def test_every_reader_refuses_a_damaged_store_whatever_force_says(synth_world, tmp_path, ga3ce):
    from ga3ce_prep.errors import StoreError
    from ga3ce_prep.train.dataset import ContextDataset

    store, run = _store_and_run(synth_world, tmp_path)
    fid = open_store(store).frames["id"][0]
    (store / "frames" / "head_pos" / "c" / "0" / "0").unlink()           # one chunk deleted
    damaged = f"error: {store} is damaged: array frames/head_pos, chunk (0, 0) (rows 0-11): missing"
    rebuild = ("rerunning the `ga3ce-prep run` command that wrote it (its work directory's cache makes that quick): "
               "`ga3ce-prep run --pipeline ")
    ckpt = run / "best.pt"
    for args in (["eval", "--store", store, "--checkpoint", ckpt, "--cdf", "none"],
                 ["eval", "--store", store, "--checkpoint", ckpt, "--cdf", "none", "--force"],
                 ["train", "--store", store, "--out", tmp_path / "run2", "--epochs", "1"],
                 ["train", "--store", store, "--out", tmp_path / "run3", "--epochs", "1", "--n-max", "auto"],
                 ["ablate", "--store", store, "--out", tmp_path / "ablate", "--rows", "full", "--epochs", "1"],
                 ["report", run, "--out", tmp_path / "report"],
                 ["report", run, "--out", tmp_path / "report", "--force"],
                 ["info", store], ["show", store, fid, "--out", tmp_path / "f.png"],
                 ["export", store, tmp_path / "s.h5"]):
        line = refused(ga3ce(*args), None, damaged, rebuild, f"--out {store}`, with the --set options it had")
        assert line.startswith(damaged), (args, line)
    with pytest.raises(StoreError, match=r"array frames/head_pos, chunk \(0, 0\)"):
        ContextDataset(store, "train")
    assert not list(tmp_path.rglob("eval_*")) and not list(tmp_path.rglob("config.json"))[1:]
    assert not (tmp_path / "f.png").exists() and not (tmp_path / "s.h5").exists()
    assert not (tmp_path / "report" / "index.html").exists()
    env = {k: v for k, v in os.environ.items() if k != "GA3CE_DEBUG"}
    p = subprocess.run([str(Path(sys.executable).parent / "ga3ce-prep"), "eval", "--store", str(store), "--checkpoint",
                        str(ckpt), "--cdf", "none", "--force"], capture_output=True, text=True, timeout=300, env=env)
    refused((p.returncode, p.stdout, p.stderr), None, damaged, rebuild)


# ---------------------------------------------------------------- the weak three

def test_a_header_only_annotation_beside_images_is_said(synth_world, tmp_path, ga3ce, caplog):
    data = _copy(synth_world, tmp_path)
    ann = data / "train_annotation.txt"
    ann.write_text(ann.read_text().splitlines()[0] + "\n")               # GFIE's file, its rows gone
    n = len(list((data / "rgb" / "train").rglob("*.jpg")))
    code, _, err = _run(ga3ce, data, tmp_path / "s.zarr")
    assert code == 0, err
    assert (f"gfie: {ann} has a header and no rows, but {data / 'rgb' / 'train'} holds {n} images: the train split "
            "is empty; write its rows, or leave it out with dataset.options.splits") in caplog.text
    assert n and not len(open_store(tmp_path / "s.zarr").indices("train"))
    caplog.clear()
    shutil.rmtree(data / "rgb" / "train")                                 # no images: an empty split, said nothing
    code, _, err = _run(ga3ce, data, tmp_path / "t.zarr")
    assert code == 0, err
    assert "has a header and no rows" not in caplog.text


@pytest.mark.parametrize("kind, found", [
    ("text", "it holds text ('525.0 525.0 80.0 60.0')"),
    ("pickle", "it holds a Python pickle"),
    ("objects", "it holds Python objects (dtype object)"),
])
def test_intrinsics_that_are_not_a_numeric_npy_are_refused_for_what_they_are(synth_world, tmp_path, ga3ce, kind,
                                                                             found):
    data = _copy(synth_world, tmp_path)
    k = data / "CameraKinect.npy"
    values = [525.0, 525.0, 80.0, 60.0]
    if kind == "text":
        k.write_text(" ".join(map(str, values)) + "\n")
    elif kind == "pickle":
        k.write_bytes(pickle.dumps(values))
    else:
        np.save(k, np.array([*values[:3], "60"], dtype=object), allow_pickle=True)
    line = refused(_run(ga3ce, data, tmp_path / "s.zarr"), tmp_path / "s.zarr",
                   f"cannot read intrinsics {k}: not a numeric .npy array: {found}; pickled objects are never loaded; "
                   "expected a .npy of 4 floats [fx, fy, cx, cy]")
    assert "allow_pickle" not in line and "unsafely" not in line
