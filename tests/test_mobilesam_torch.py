"""The torch runtime (`runtime: torch`) against the ONNX path, on the random-weight MobileSAM (seed 0):
the ONNX files and the `mobile_sam.pt` of the same weights that `ga3ce_prep.testing.mobilesam_random`
builds; MobileSAM's code from `estimators/segment/mobilesam_code.py`'s private folder."""
import re
import sys

import numpy as np
import pytest

from ga3ce_prep.errors import ConfigError, ModelFileError
from ga3ce_prep.estimators.segment import mobilesam_code
from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
from ga3ce_prep.estimators.segment.mobilesam_runners import (
    MaskDecoder,
    OfficialDecoder,
    SegmenterOptions,
    single_point_prompts,
)
from ga3ce_prep.testing import mobilesam_random
from ga3ce_prep.testing.scripted import drawn_frame

ENC, DEC = mobilesam_random.ensure()
CKPT = mobilesam_random.checkpoint()
mobilesam_code.install()
# Permissive thresholds, as tests/test_mobilesam_models.py: random weights then keep many masks
MANY = dict(points_per_side=5, pred_iou_thresh=0.0, stability_score_thresh=0.3, stability_score_offset=0.05,
            box_nms_thresh=1.0, threads=1)


def torch_options(**kw) -> SegmenterOptions:
    return SegmenterOptions(**{**MANY, "runtime": "torch", **kw})


@pytest.fixture(scope="module")
def segmenters():
    return (MobileSamSegmenter(ENC, DEC, SegmenterOptions(**MANY)),
            MobileSamSegmenter.from_checkpoint(CKPT, torch_options()))


def test_torch_decoder_gives_the_decoder_onnxs_ious_and_logits(segmenters):
    onnx_seg, torch_seg = segmenters
    assert isinstance(torch_seg.decoder, MaskDecoder) and torch_seg.mask_mode == "multimask"
    emb = onnx_seg.encoder.embed(drawn_frame())
    np.testing.assert_allclose(torch_seg.encoder.embed(drawn_frame()), emb, rtol=0, atol=1e-4)
    coords, labels = single_point_prompts(np.random.default_rng(0).uniform(0, 1024, (9, 2)))
    ref_iou, ref_low = OfficialDecoder(DEC, ["CPUExecutionProvider"], 1)(
        emb, coords, labels, (1024, 1024), outputs=("iou_predictions", "low_res_masks"))
    torch_seg.decoder.set_image(emb)
    iou, state = torch_seg.decoder.predict_iou(coords, labels)
    assert np.abs(iou - ref_iou).max() < 1e-4
    assert np.abs(torch_seg.decoder.low_res_masks(state, np.array([8, 0])) - ref_low[[8, 0]]).max() < 1e-4
    got = torch_seg.decoder.candidate_masks(state, np.array([3, 3, 5]), np.array([1, 3, 2]))
    assert np.abs(got - ref_low[[3, 3, 5], [1, 3, 2]]).max() < 1e-4 and np.abs(ref_low).max() > 0.1


def test_torch_decoder_embeds_box_corners_as_the_decoder_onnx(segmenters):
    """Box prompts (click, then corners labelled 2 and 3: prompts.Prompts.decoder_inputs): the torch
    decoder adds the corner embeddings as segment-anything's `_embed_boxes` and the ONNX export do."""
    from ga3ce_prep.estimators.segment.prompts import Prompts

    onnx_seg, torch_seg = segmenters
    emb = onnx_seg.encoder.embed(drawn_frame())
    boxes = np.array([[100.0, 80.0, 300.0, 260.0], [350.0, 200.0, 600.0, 470.0], [0.0, 0.0, 639.0, 479.0]])
    coords, labels = Prompts(0.5 * (boxes[:, :2] + boxes[:, 2:]), boxes).decoder_inputs((480, 640))
    ref_iou, ref_low = OfficialDecoder(DEC, ["CPUExecutionProvider"], 1)(
        emb, coords, labels, (1024, 1024), outputs=("iou_predictions", "low_res_masks"))
    torch_seg.decoder.set_image(emb)
    iou, state = torch_seg.decoder.predict_iou(coords, labels)
    assert np.abs(iou - ref_iou).max() < 1e-4
    assert np.abs(torch_seg.decoder.low_res_masks(state, np.arange(3)) - ref_low).max() < 1e-4


def test_torch_runtime_keeps_the_onnx_paths_masks(segmenters):
    """The whole generator, 640x480, 5x5 grid, permissive thresholds: the same candidates, and the
    kept masks within the tolerance the ONNX path holds against the reference order
    (tests/test_mobilesam_models.py::test_generator_keeps_the_reference_candidates)."""
    rgb = drawn_frame()
    a, b = (seg.segment(rgb) for seg in segmenters)
    assert a.n_candidates == b.n_candidates == 75 and 5 < len(a.masks) == len(b.masks) < 75
    np.testing.assert_array_equal(b.points, a.points)
    np.testing.assert_allclose(b.scores, a.scores, atol=1e-5)
    np.testing.assert_allclose(b.stability, a.stability, atol=2e-3)
    assert np.abs(b.boxes - a.boxes).max() <= 1
    diff = (a.masks != b.masks).reshape(len(a.masks), -1).sum(axis=1)
    assert diff.max() <= 0.001 * 480 * 640


def test_clear_errors_for_the_checkpoint_the_code_and_the_device(tmp_path, monkeypatch):
    with pytest.raises(ModelFileError, match=re.escape(str(tmp_path / "nope.pt"))):
        MobileSamSegmenter.from_checkpoint(tmp_path / "nope.pt", torch_options())
    bad = tmp_path / "other.pt"
    bad.write_bytes(b"not a state dict")
    with pytest.raises(ModelFileError, match="other.pt does not load"):
        MobileSamSegmenter.from_checkpoint(bad, torch_options())
    with pytest.raises(ConfigError, match="leave out providers"):
        MobileSamSegmenter.from_checkpoint(CKPT, torch_options(providers="cuda"))
    with pytest.raises(ConfigError, match="runtime: torch"):
        MobileSamSegmenter(ENC, DEC, SegmenterOptions(device="cuda"))
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA device"):
            MobileSamSegmenter.from_checkpoint(CKPT, torch_options(device="cuda"))
    monkeypatch.setitem(sys.modules, "mobile_sam", None)         # MobileSAM's code in neither place
    monkeypatch.setenv("GA3CE_MOBILESAM_CODE", str(tmp_path / "empty"))
    with pytest.raises(ConfigError) as e:
        MobileSamSegmenter.from_checkpoint(CKPT, torch_options())
    assert str(CKPT) in str(e.value) and mobilesam_code.INSTALL_COMMAND in str(e.value)


def test_backend_runs_the_checkpoint_and_names_it(synth_world):
    """objects/mobilesam with runtime: torch: checked before any work, the same masks as the ONNX
    backend on a synthetic frame, the checkpoint's SHA-256 in the provenance; files of the other
    runtime are refused naming the keys."""
    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.files import file_sha256
    from ga3ce_prep.stages import backend_class
    from ga3ce_prep.stages.base import BackendContext

    ctx = BackendContext(synth_world)
    cls = backend_class("objects", "mobilesam")
    params = {"points_per_side": 3, "pred_iou_thresh": 0.0, "stability_score_thresh": 0.0, "box_nms_thresh": 1.0}
    b = cls({"runtime": "torch", "checkpoint": str(CKPT), **params}, ctx)
    b.check()
    prov = b.provenance()
    assert prov["models"] == {str(CKPT): file_sha256(CKPT)} and prov["mask_mode"] == "multimask"
    frame = next(iter(open_dataset("gfie", synth_world)))
    depth = backend_class("depth", "oracle")({"truth": str(synth_world / "truth.h5")}, ctx).depth(frame)
    masks, scores = b.masks(frame, depth)
    ref_masks, ref_scores = cls({"encoder": str(ENC), "decoder": str(DEC), **params}, ctx).masks(frame, depth)
    assert len(masks) == len(ref_masks) > 0 and masks.shape[1:] == depth.depth.shape
    np.testing.assert_allclose(scores, ref_scores, atol=1e-5)
    assert (masks != ref_masks).reshape(len(masks), -1).mean(axis=1).max() <= 1e-3
    for wrong, key in (({"runtime": "torch", "checkpoint": str(CKPT), "encoder": str(ENC)}, "leave out encoder"),
                       ({"runtime": "torch"}, "needs checkpoint"),
                       ({"checkpoint": str(CKPT)}, "set runtime: torch")):
        with pytest.raises(ConfigError, match=key):
            cls(wrong, ctx).check()


def test_depth_prompts_on_the_torch_runtime_keep_the_onnx_paths_masks(synth_world):
    """prompts: depth with runtime: torch: the same prompts, the same masks as on ONNX Runtime."""
    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.stages import backend_class
    from ga3ce_prep.stages.base import BackendContext

    ctx = BackendContext(synth_world)
    cls = backend_class("objects", "mobilesam")
    params = {"prompts": "depth", "prompt_boxes": True, "pred_iou_thresh": 0.0, "stability_score_thresh": 0.0,
              "box_nms_thresh": 1.0}
    frame = next(iter(open_dataset("gfie", synth_world)))
    depth = backend_class("depth", "oracle")({"truth": str(synth_world / "truth.h5")}, ctx).depth(frame)
    masks, scores = cls({"runtime": "torch", "checkpoint": str(CKPT), **params}, ctx).masks(frame, depth)
    ref_masks, ref_scores = cls({"encoder": str(ENC), "decoder": str(DEC), **params}, ctx).masks(frame, depth)
    assert len(masks) == len(ref_masks) > 3
    np.testing.assert_allclose(scores, ref_scores, atol=1e-5)
    assert (masks != ref_masks).reshape(len(masks), -1).mean(axis=1).max() <= 1e-3
