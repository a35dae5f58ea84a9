"""`ga3ce-prep run` with `objects: mobilesam` end to end on the synthetic world, with the official
MobileSAM architecture's ONNX files (random weights: permissive thresholds so masks survive)."""
import numpy as np
import pytest
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
from ga3ce_prep.estimators.segment.mobilesam_runners import SegmenterOptions
from ga3ce_prep.frames import load_rgb
from ga3ce_prep.geometry import object_positions
from ga3ce_prep.store import open_store
from ga3ce_prep.testing import mobilesam_random

ENC, DEC = mobilesam_random.ensure()
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


def test_reuse_sequence_runs_per_shard_and_is_named_in_the_provenance(synth_world, tmp_path):
    """reuse: sequence through the pipeline: each shard's first frame of a sequence is a key frame
    (the state starts afresh per shard), later frames reuse; the provenance names the generator."""
    import threading

    from ga3ce_prep.stages import backend_class
    from ga3ce_prep.stages.base import BackendContext

    out = tmp_path / "r.zarr"
    args = ["run", "-p", "synthetic-mobilesam", "-d", str(synth_world), "-o", str(out), "--limit", "4", "-q",
            "--set", f"stages.objects.params.encoder={ENC}", "--set", f"stages.objects.params.decoder={DEC}",
            "--set", "stages.objects.params.reuse=sequence",
            *[a for k, v in PARAMS.items() for a in ("--set", f"stages.objects.params.{k}={v}")]]
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    store = open_store(out)
    assert len(store) == 4 and "reuse: sequence" in str(store.attrs)
    # the backend itself: one sequence's frames in order, then a new shard
    frames = sorted(open_dataset("gfie", synth_world), key=lambda f: (f.sequence, f.index))[:3]
    b = backend_class("objects", "mobilesam")({"encoder": str(ENC), "decoder": str(DEC), "reuse": "sequence",
                                                "reuse_max_changed": 1.0, **PARAMS}, BackendContext(synth_world))
    depth = backend_class("depth", "oracle")({"truth": str(synth_world / "truth.h5")}, BackendContext(synth_world))
    seq = lambda: b._sequences[threading.get_ident()][frames[0].sequence].last  # noqa: E731
    b.start_shard()
    steps = []
    for f in frames:
        b.masks(f, depth.depth(f))
        steps.append(seq().key)
    b.start_shard()
    b.masks(frames[2], depth.depth(frames[2]))
    assert steps + [seq().key] == [True, False, False, True]   # (random weights: every prompt changed, but
    # reuse_max_changed 1 keeps the key frame)
    assert b.provenance()["generator"] == "reuse: sequence"


def test_reuse_runs_have_their_own_cache_version(synth_world):
    """A change of reuse's defaults changes reuse outputs for the same written parameters: the objects
    stage's cache key moves for reuse runs only, exact runs keep their entries."""
    from ga3ce_prep.pipeline.config import load_pipeline
    from ga3ce_prep.pipeline.run import stage_identity
    from ga3ce_prep.stages.objects_mobilesam import MobileSAMObjects

    def ident(*sets):
        files = [f"stages.objects.params.encoder={ENC}", f"stages.objects.params.decoder={DEC}"]
        return stage_identity(load_pipeline("synthetic-mobilesam", synth_world, overrides=[*files, *sets],
                                            check_files=False), "objects")

    exact, reuse = ident(), ident("stages.objects.params.reuse=sequence")
    assert exact["version"] == MobileSAMObjects.version == ident("stages.objects.params.reuse=off")["version"]
    assert reuse["version"] == f"{MobileSAMObjects.version}+reuse{MobileSAMObjects.REUSE_VERSION}"


def test_depth_prompts_run_through_the_pipeline_with_reuse(synth_world, tmp_path):
    """prompts: depth: the backend prompts the frame's depth segments (a click each, grid points on the
    clusters), alone and under reuse: sequence; the store's provenance names them, the cache key carries
    their own version, and image crops are refused."""
    import threading

    from ga3ce_prep.errors import ConfigError
    from ga3ce_prep.estimators.segment.depth_prompts import depth_prompts
    from ga3ce_prep.estimators.segment.geometric import GeometricParams
    from ga3ce_prep.pipeline.config import load_pipeline
    from ga3ce_prep.pipeline.run import stage_identity
    from ga3ce_prep.stages import backend_class
    from ga3ce_prep.stages.base import BackendContext
    from ga3ce_prep.stages.objects import frame_segments
    from ga3ce_prep.stages.objects_mobilesam import MobileSAMObjects

    files = [f"stages.objects.params.encoder={ENC}", f"stages.objects.params.decoder={DEC}"]
    sets = [*files, "stages.objects.params.prompts=depth",
            *[f"stages.objects.params.{k}={v}" for k, v in PARAMS.items()]]
    out = tmp_path / "d.zarr"
    args = ["run", "-p", "synthetic-mobilesam", "-d", str(synth_world), "-o", str(out), "--limit", "2", "-q"]
    res = CliRunner().invoke(cli, args + [a for s in sets for a in ("--set", s)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    store = open_store(out)
    assert store.attrs["stages"]["objects"]["prompts"] == "depth" and store.frames["obj_count"].sum() > 0
    # the backend's prompts are the rule's on the frame's segments
    ctx = BackendContext(synth_world)
    params = {"encoder": str(ENC), "decoder": str(DEC), "prompts": "depth", **PARAMS}
    b = backend_class("objects", "mobilesam")(params, ctx)
    frames = sorted(open_dataset("gfie", synth_world), key=lambda f: (f.sequence, f.index))[:3]
    depth = backend_class("depth", "oracle")({"truth": str(synth_world / "truth.h5")}, ctx)
    d = depth.depth(frames[0])
    rgb = load_rgb(frames[0].image_path)
    prompts = depth_prompts(frame_segments(frames[0], d, GeometricParams()), rgb.shape[:2], b.p)
    r = b.estimator().segment(rgb, out_size=d.depth.shape, prompts=prompts)
    masks, scores = b.masks(frames[0], d)
    assert r.n_prompts == len(prompts) > 0
    np.testing.assert_array_equal(masks, r.masks)
    np.testing.assert_array_equal(scores, r.scores)
    # reuse: sequence over depth prompts: a key frame, then reuse frames (every prompt may change: random weights)
    br = backend_class("objects", "mobilesam")({**params, "reuse": "sequence", "reuse_max_changed": 1.0}, ctx)
    br.start_shard()
    steps = []
    for f in frames:
        br.masks(f, depth.depth(f))
        steps.append(br._sequences[threading.get_ident()][f.sequence].last.key)
    assert steps == [True, False, False]
    assert br.provenance()["generator"] == "reuse: sequence" and br.provenance()["prompts"] == "depth"

    def ident(*more):
        return stage_identity(load_pipeline("synthetic-mobilesam", synth_world, overrides=[*files, *more],
                                            check_files=False), "objects")["version"]

    v, depth_v = MobileSAMObjects.version, f"+depth{MobileSAMObjects.PROMPTS_VERSION}"
    assert ident() == v and ident("stages.objects.params.prompts=depth") == v + depth_v
    assert ident("stages.objects.params.prompts=depth", "stages.objects.params.reuse=sequence") == \
        f"{v}{depth_v}+reuse{MobileSAMObjects.REUSE_VERSION}"
    with pytest.raises(ConfigError, match="prompts: depth prompts the full image only"):
        backend_class("objects", "mobilesam")({**params, "crop_n_layers": 1}, ctx).check()
