"""`ga3ce-prep run` with `objects: mobilesam` end to end on the synthetic world, with the official
MobileSAM architecture's ONNX files (random weights: permissive thresholds so masks survive)."""
import numpy as np
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.estimators.mobilesam import MobileSamSegmenter, SegmenterOptions
from ga3ce_prep.frames import load_rgb
from ga3ce_prep.geometry import object_positions
from ga3ce_prep.store import open_store
from test_mobilesam_models import DEC, ENC

PARAMS = {"points_per_side": 3, "pred_iou_thresh": 0.0, "stability_score_thresh": 0.0, "box_nms_thresh": 1.0}


def test_run_with_mobilesam_objects(synth_world, tmp_path):
    out = tmp_path / "s.zarr"
    sets = [f"stages.objects.params.encoder={ENC}", f"stages.objects.params.decoder={DEC}",
            *[f"stages.objects.params.{k}={v}" for k, v in PARAMS.items()]]
    args = ["run", "-p", "synthetic-mobilesam", "-d", str(synth_world), "-o", str(out), "--limit", "2", "-q"]
    for s in sets:
        args += ["--set", s]
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    store = open_store(out)
    assert len(store) == 2 and "mobilesam" in str(store.attrs)
    # frame 0 again, straight through the segmenter and the shared back-projection
    from ga3ce_prep.pipeline.config import load_pipeline
    conf = load_pipeline("synthetic-mobilesam", synth_world, check_files=False)
    frame = next(iter(open_dataset(conf.dataset_format, synth_world, **conf.dataset_options)))
    i = list(store.frames["id"]).index(frame.id)
    seg = MobileSamSegmenter(ENC, DEC, SegmenterOptions(**PARAMS))
    depth_backend = conf.stages["depth"].make(synth_world)
    depth = depth_backend.depth(frame)
    r = seg.segment(load_rgb(frame.image_path), out_size=depth.depth.shape)
    assert len(r.masks) == 27 and r.masks.shape[1:] == depth.depth.shape
    pos = object_positions(depth.depth, frame.K, r.masks, valid=depth.valid, min_points=10)
    s, n = int(store.frames["obj_start"][i]), int(store.frames["obj_count"][i])
    assert n == len(pos.xyz) > 0
    np.testing.assert_allclose(store.objects["xyz"][s:s + n], pos.xyz, atol=1e-5)
    np.testing.assert_allclose(store.objects["score"][s:s + n], r.scores[pos.index], atol=1e-6)


def test_backend_builds_its_segmenter_once_per_process_and_leaves_it_out_of_pickles(synth_world):
    import pickle

    from ga3ce_prep.stages import backend_class
    from ga3ce_prep.stages.base import BackendContext

    ctx = BackendContext(synth_world)
    b = backend_class("objects", "mobilesam")({"encoder": str(ENC), "decoder": str(DEC), **PARAMS}, ctx)
    b.warm()
    seg = b.estimator()
    assert isinstance(seg, MobileSamSegmenter) and b.estimator() is seg
    frame = next(iter(open_dataset("gfie", synth_world)))
    depth = backend_class("depth", "oracle")({"truth": str(synth_world / "truth.h5")}, ctx).depth(frame)
    masks, scores = b.masks(frame, depth)
    clone = pickle.loads(pickle.dumps(b))                          # sessions stay behind
    assert getattr(clone, "_estimator", None) is None
    again, again_scores = clone.masks(frame, depth)
    np.testing.assert_array_equal(again, masks)
    np.testing.assert_array_equal(again_scores, scores)
