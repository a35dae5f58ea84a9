"""The fast decoder and the generator against the official MobileSAM ONNX files (random weights, seed 0),
which `ga3ce_prep.testing.mobilesam_random` builds once from registry packages and verifies."""
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from ga3ce_prep.estimators.segment.fast_decoder import FastDecoder
from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
from ga3ce_prep.estimators.segment.mobilesam_runners import MaskDecoder, OfficialDecoder, SegmenterOptions
from ga3ce_prep.testing import mobilesam_random
from ga3ce_prep.testing.amg_reference import reference_generate
from ga3ce_prep.testing.scripted import drawn_frame

ENC, DEC = mobilesam_random.ensure()
CPU = ["CPUExecutionProvider"]   # the runners' providers and threads: (CPU, 1)


def perturbed_decoder(path: Path, seed: int = 1) -> onnx.ModelProto:
    """The official decoder with random LayerNorm / LayerNorm2d scales and shifts. The random-weight
    export keeps torch's init (1 and 0), shared through Identity nodes, which would leave the fast
    decoder's LayerNorm algebra untested."""
    m = onnx.load(str(path))
    g, rng = m.graph, np.random.default_rng(seed)
    dims = {t.name: list(t.dims) for t in g.initializer}
    nodes = []
    for n in g.node:
        if n.op_type == "Identity" and "norm" in n.output[0] and n.input[0] in dims:
            mean = 1.0 if n.output[0].endswith("weight") else 0.0
            g.initializer.append(numpy_helper.from_array(
                rng.normal(mean, 0.3, dims[n.input[0]]).astype(np.float32), n.output[0]))
        else:
            nodes.append(n)
    del g.node[:]
    g.node.extend(nodes)
    for t in g.initializer:
        if t.name.endswith("layers.0.norm1.weight") or t.name.endswith("layers.0.norm1.bias") \
                or t.name in ("onnx::Mul_1771", "onnx::Add_1773"):
            a = numpy_helper.to_array(t)
            t.CopyFrom(numpy_helper.from_array((a + rng.normal(0, 0.3, a.shape)).astype(np.float32), t.name))
    return m


def prompt_grid():
    """Single points (+ padding point), as segment-everything uses them, and a few multi-point and box
    prompts (labels 0/1, box corners 2/3)."""
    xs = np.linspace(20, 1000, 4)
    single = [([[x, y], [0, 0]], [1, -1]) for x in xs for y in np.linspace(30, 740, 3)]
    multi = [([[100, 200], [600, 500], [0, 0]], [1, 0, -1]), ([[300, 300], [700, 650], [500, 420]], [2, 3, 1])]
    return single, multi


@pytest.fixture(scope="module")
def embedding():
    from ga3ce_prep.estimators.segment.mobilesam_runners import ImageEncoder
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (480, 640, 3)).astype(np.uint8)
    return ImageEncoder(ENC, CPU, 1).embed(rgb)


@pytest.mark.parametrize("perturb", [False, True])
def test_fast_decoder_equals_official_decoder(embedding, tmp_path, perturb):
    path = DEC
    if perturb:
        path = tmp_path / "decoder_ln.onnx"
        onnx.save(perturbed_decoder(DEC), path)
    official, fast = OfficialDecoder(path, CPU, 1), FastDecoder(path, CPU, 1)
    fast.set_image(embedding)
    for prompts in prompt_grid():
        coords = np.array([p[0] for p in prompts], np.float32)
        labels = np.array([p[1] for p in prompts], np.float32)
        ref_iou, ref_low = official(embedding, coords, labels, (480, 640), outputs=("iou_predictions", "low_res_masks"))
        iou, state = fast.predict_iou(coords, labels)
        assert np.abs(iou - ref_iou).max() < 1e-4
        sel = np.array([len(coords) - 1, 0])       # any subset, in any order
        low = fast.low_res_masks(state, sel)
        assert low.shape == (2, 4, 256, 256)
        assert np.abs(low - ref_low[sel]).max() < 1e-4
        assert np.abs(ref_low).max() > 0.1        # not trivially zero


def test_generator_keeps_the_reference_candidates():
    """Permissive thresholds (IoU filter off, stability offset 0.05 so scores spread, NMS off): the
    fast generator decodes the same candidates with the same predicted IoUs and stability scores and
    keeps the same masks, in the same order, as the reference order on the official files."""
    rgb = drawn_frame()
    opt = SegmenterOptions(points_per_side=5, pred_iou_thresh=0.0, stability_score_thresh=0.3,
                           stability_score_offset=0.05, box_nms_thresh=1.0)
    seg = MobileSamSegmenter(ENC, DEC, opt)
    fast = seg.segment(rgb)
    ref = reference_generate(seg.encoder, seg.official, rgb, opt)
    assert len(ref.candidates) == 75 and fast.n_candidates == 75
    assert 5 < len(ref.masks) < 75                  # the stability filter keeps some, drops others
    assert len(fast.masks) == len(ref.masks)
    np.testing.assert_allclose(fast.scores, ref.scores, atol=1e-5)
    np.testing.assert_allclose(fast.stability, ref.stability, atol=2e-3)
    np.testing.assert_array_equal(fast.points, ref.points)
    assert np.abs(fast.boxes - ref.boxes).max() <= 1
    diff = (fast.masks != ref.masks).reshape(len(ref.masks), -1).sum(axis=1)
    assert diff.max() <= 0.001 * 480 * 640          # float noise at the 0 threshold only
    # with the defaults random weights pass nothing (predicted IoUs far below 0.88), as in the reference
    seg.options = SegmenterOptions(points_per_side=5)
    assert len(seg.segment(rgb).masks) == 0


def test_mask_graph_gelus_take_no_separate_bias(tmp_path):
    """The second transposed conv's bias rides in its matrix product (a ones column), so ONNX Runtime's
    optimized mask graph has two plain Gelu nodes per pixel slice (the CPU graph's slices) and no Add
    before a Gelu nor a BiasGelu (docs/studies/2026-11-29-segment-everything-speed.md, "What was tried":
    the separate bias pass cost more than the concat)."""
    import onnxruntime as ort

    from ga3ce_prep.estimators.runtime.onnx_runtime import session_options
    from ga3ce_prep.estimators.segment.fast_decoder import FastDecoder
    from ga3ce_prep.estimators.segment.fast_decoder_graphs import Derived, build_mask_graph
    from ga3ce_prep.estimators.segment.fast_decoder_weights import decoder_weights

    w = decoder_weights(DEC)
    so = session_options(1)
    so.optimized_model_filepath = str(tmp_path / "opt.onnx")
    chunks = FastDecoder.CPU_MASK_PIXEL_CHUNKS
    ort.InferenceSession(build_mask_graph(w, Derived.from_weights(w), chunks).SerializeToString(), so,
                         providers=["CPUExecutionProvider"])
    nodes = onnx.load(so.optimized_model_filepath).graph.node
    made_by = {o: n.op_type for n in nodes for o in n.output}
    gelus = [n for n in nodes if n.op_type in ("Gelu", "BiasGelu")]
    assert chunks > 1 and [n.op_type for n in gelus] == ["Gelu", "Gelu"] * chunks
    assert all(made_by.get(n.input[0]) != "Add" for n in gelus)


def test_graphs_in_pixel_slices_give_the_whole_images_outputs():
    """The token and mask graphs cut into pixel slices (the CPU graphs: the softmaxes over the pixels
    streamed over the slices) compute what the graphs over the whole image compute, for 1 and 3
    prompts, and so do mask-graph calls of at most 2 prompts; a slice count that does not divide the
    4096 pixels is refused."""
    import onnxruntime as ort

    from ga3ce_prep.estimators.segment.fast_decoder_graphs import STATE, TOKEN_IMAGE_INPUTS, Derived, build_mask_graph
    from ga3ce_prep.estimators.segment.fast_decoder_tokens import build_token_graph
    from ga3ce_prep.estimators.segment.fast_decoder_weights import decoder_weights

    dec = FastDecoder(DEC, CPU, 1)
    assert dec.CPU_TOKEN_PIXEL_CHUNKS > 1 and dec.CPU_MASK_PIXEL_CHUNKS > 1
    dec.set_image(np.random.default_rng(3).standard_normal((1, 256, 64, 64)).astype(np.float32))
    coords = np.array([[[100.0, 200.0], [0, 0]], [[900.0, 50.0], [0, 0]], [[512.0, 700.0], [0, 0]]], np.float32)
    labels = np.array([[1, -1]] * 3, np.float32)
    iou, state = dec.predict_iou(coords, labels)
    w = decoder_weights(DEC)
    d = Derived.from_weights(w)
    tokens = ort.InferenceSession(build_token_graph(w, d, 1).SerializeToString(), providers=CPU)
    whole = tokens.run(["iou_predictions", *STATE], {**{k: dec._img[k].numpy() for k in TOKEN_IMAGE_INPUTS},
                                                      "point_coords": coords, "point_labels": labels})
    np.testing.assert_allclose(iou, whole[0], rtol=0, atol=2e-6)
    for name, ref in zip(STATE, whole[1:]):
        np.testing.assert_allclose(state[name].numpy(), ref, rtol=1e-5, atol=1e-6, err_msg=name)
    masks = ort.InferenceSession(build_mask_graph(w, d, 1).SerializeToString(), providers=CPU)
    for index in ([1], [0, 1, 2]):
        ref = masks.run(["low_res_raw"], {**{k: v.numpy() for k, v in state.items()}, "SC": dec._img["SC"].numpy(),
                                          "index": np.array(index, np.int64)})[0]
        got = dec.low_res_raw(state, np.array(index))
        assert got.shape == ref.shape == (len(index), 4096 * 16, 4) and np.abs(ref).max() > 0.01
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)
    dec.mask_batch = 2   # the prompts in mask-graph calls of at most 2
    np.testing.assert_allclose(dec.low_res_raw(state, np.array([2, 0, 1])), ref[[2, 0, 1]], rtol=0, atol=1e-6)
    for build in (build_token_graph, build_mask_graph):
        with pytest.raises(ValueError, match="divide 4096"):
            build(w, d, 3)


def test_fast_decoder_graphs_copy_nothing_into_outputs_and_transpose_no_attention(tmp_path):
    """The attentions are held as a0cT (a free reshape) and read through transposed products that
    ONNX Runtime fuses (docs/models/segment-everything.md, "How the fast decoder is fast", Layout), and
    outputs are written by the nodes that compute them: the optimized token and mask graphs have no
    Identity, no transpose of a (B, H, T, P) attention (cat_heads' perm) and no last-two-axes transpose
    left unfused."""
    import onnxruntime as ort

    from ga3ce_prep.estimators.runtime.onnx_runtime import session_options
    from ga3ce_prep.estimators.segment.fast_decoder_graphs import Derived, build_mask_graph
    from ga3ce_prep.estimators.segment.fast_decoder_tokens import build_token_graph
    from ga3ce_prep.estimators.segment.fast_decoder_weights import decoder_weights

    w = decoder_weights(DEC)
    d = Derived.from_weights(w)
    for name, model in (("tokens", build_token_graph(w, d)), ("tokens in 4 pixel slices", build_token_graph(w, d, 4)),
                        ("masks", build_mask_graph(w, d)), ("masks in 4 pixel slices", build_mask_graph(w, d, 4))):
        so = session_options(1)
        so.optimized_model_filepath = str(tmp_path / f"{name}.onnx")
        ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])
        nodes = onnx.load(so.optimized_model_filepath).graph.node
        made_by = {o: n.op_type for n in nodes for o in n.output}
        transposes = [n for n in nodes if n.op_type == "Transpose"]
        perms = [list(a.ints) for n in transposes for a in n.attribute if a.name == "perm"]
        fused = [n for n in nodes if n.op_type == "FusedMatMul"
                 and any(a.name in ("transA", "transB") and a.i for a in n.attribute)]
        assert not [n for n in nodes if n.op_type == "Identity"], name
        if name.startswith("tokens"):
            assert [0, 3, 1, 2] not in perms and [0, 2, 1] not in perms, perms
            assert len(fused) >= 8
        else:   # the (K, 2HT + 2, P) left side, concatenated (and sliced), is read through transA
            assert not [n for n in transposes if made_by.get(n.input[0]) in ("Concat", "Slice", "Split")]
            assert len(fused) == (4 if "slices" in name else 1)


def test_graph_builder_outputs_rename_their_producer():
    """GraphBuilder.output renames the producing node's output (no copy), keeps later uses of the old
    name working, and falls back to an Identity for an input or a value exposed twice."""
    import onnxruntime as ort

    from ga3ce_prep.estimators.runtime.onnx_graph import GraphBuilder

    g = GraphBuilder("t")
    x = g.input("x", [2])
    y = g.mul(x, g.const([2.0, 3.0]))
    g.output(y, "a")
    g.output(g.add(y, g.const(1.0)), "b")           # y used after it was exposed
    g.output(y, "c")                                # exposed twice
    g.output(x, "d")                                # a graph input
    model = g.model()
    assert [n.op_type for n in model.graph.node].count("Identity") == 2
    outs = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(
        ["a", "b", "c", "d"], {"x": np.array([1.0, 2.0], np.float32)})
    np.testing.assert_array_equal(np.stack(outs), [[2, 6], [3, 7], [2, 6], [1, 2]])


def test_fast_decoder_batch_size_follows_the_provider():
    assert FastDecoder(DEC, CPU, 1).batch_size == FastDecoder.CPU_BATCH_SIZE == 8


def test_both_decoders_are_mask_decoders():
    assert isinstance(FastDecoder(DEC, CPU, 1), MaskDecoder)
    assert isinstance(OfficialDecoder(DEC, CPU, 1, batch_size=64), MaskDecoder)


def test_io_binding_is_chosen_by_the_provider():
    from ga3ce_prep.estimators.segment.fast_decoder import use_io_binding

    assert use_io_binding("auto", ["CUDAExecutionProvider", "CPUExecutionProvider"])
    assert not use_io_binding("auto", CPU)
    assert use_io_binding("on", CPU) and not use_io_binding("off", ["CUDAExecutionProvider"])
    dec = FastDecoder(DEC, CPU, 1, io_binding=True)
    assert dec.batch_size is None and dec.device == "cpu"


def test_io_binding_gives_the_plain_paths_masks(monkeypatch):
    """The I/O binding path (all prompts of the crop in one token-graph call, the state bound as
    OrtValues into the mask graph, here in chunks of 7 prompts) on CPU keeps the plain path's
    candidates, scores, stability scores, boxes and masks: same graphs, the same arithmetic but for
    the batch shapes, whose kernels may sum in another order (float noise, CPU-dependent)."""
    rgb = drawn_frame()
    opt = SegmenterOptions(points_per_side=5, pred_iou_thresh=0.0, stability_score_thresh=0.3,
                           stability_score_offset=0.05, box_nms_thresh=1.0, io_binding="off")
    plain = MobileSamSegmenter(ENC, DEC, opt, verify=False)
    bound = MobileSamSegmenter(ENC, DEC, SegmenterOptions(**{**opt.to_dict(), "io_binding": "on"}), verify=False)
    assert plain.decoder.batch_size == 8 and bound.decoder.batch_size is None and bound._pool is None
    calls = []
    monkeypatch.setattr(bound.decoder, "MASK_CHUNK", 7)
    predict = bound.decoder.predict_iou
    monkeypatch.setattr(bound.decoder, "predict_iou", lambda c, lab: calls.append(len(c)) or predict(c, lab))
    a, b = plain.segment(rgb), bound.segment(rgb)
    assert calls == [25]                                        # one batch: the whole grid
    assert a.n_candidates == b.n_candidates == 75 and 5 < len(a.masks) < 75
    np.testing.assert_array_equal(b.points, a.points)
    np.testing.assert_allclose(b.scores, a.scores, atol=1e-6)
    # a stability score counts the pixels of a mask's logits above +offset over those above -offset:
    # one pixel within float noise of either flips it by about 1 / area (1.3e-6 seen on one CPU)
    np.testing.assert_allclose(b.stability, a.stability, atol=2e-5)
    np.testing.assert_array_equal(b.boxes, a.boxes)
    diff = (a.masks != b.masks).reshape(len(a.masks), -1).sum(axis=1)
    assert diff.max() <= 20                                      # logits within float noise of 0 at most


def test_built_models_are_checked(tmp_path):
    """The build's check refuses a decoder with one weight changed, an encoder with another's
    weights and a checkpoint with one weight changed: the files the tests run are the reference
    export's, not merely files that load."""
    mobilesam_random.verify(ENC.parent)   # what ensure() built passes
    m = onnx.load(str(DEC))
    t = next(t for t in m.graph.initializer if numpy_helper.to_array(t).size > 100)
    a = numpy_helper.to_array(t).copy()
    a.flat[0] += 1e-3
    t.CopyFrom(numpy_helper.from_array(a, t.name))
    onnx.save(m, str(tmp_path / mobilesam_random.DECODER))
    (tmp_path / mobilesam_random.ENCODER).symlink_to(ENC)
    with pytest.raises(RuntimeError, match="graph digest"):
        mobilesam_random.verify(tmp_path)
    (tmp_path / mobilesam_random.DECODER).unlink()
    (tmp_path / mobilesam_random.DECODER).symlink_to(DEC)
    m = onnx.load(str(ENC))
    t = next(t for t in m.graph.initializer if numpy_helper.to_array(t).size > 100)
    t.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(t) * np.float32(1.01), t.name))
    (tmp_path / mobilesam_random.ENCODER).unlink()
    onnx.save(m, str(tmp_path / mobilesam_random.ENCODER))
    with pytest.raises(RuntimeError, match="outputs differ"):
        mobilesam_random.verify(tmp_path)
    (tmp_path / mobilesam_random.ENCODER).unlink()
    (tmp_path / mobilesam_random.ENCODER).symlink_to(ENC)
    import torch

    state = torch.load(ENC.parent / mobilesam_random.CHECKPOINT, weights_only=True)
    state["mask_decoder.iou_token.weight"][0, 0] += 1e-3
    torch.save(state, tmp_path / mobilesam_random.CHECKPOINT)
    with pytest.raises(RuntimeError, match="tensor digest"):
        mobilesam_random.verify(tmp_path)
