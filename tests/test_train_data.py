"""The store Dataset, collate, bucketing, augmentation, schedule, baselines and metrics."""
import functools

import numpy as np
import pytest
import torch

from ga3ce_prep.geometry import angular_error_deg
from ga3ce_prep.model import GA3CE
from ga3ce_prep.skeleton import head_direction_from_pose
from ga3ce_prep.store import StoreWriter, open_store
from ga3ce_prep.testing.toy_store import ToyKnobs, toy_world, write_toy_store
from ga3ce_prep.train import BucketBatchSampler, ContextDataset, DatasetProfile, collate, store_fingerprint
from ga3ce_prep.train.augment import object_dropout, object_jitter, view_noise
from ga3ce_prep.train.baselines import choose_snap_cone, snap_to_object
from ga3ce_prep.train.metrics import angular_errors_2d, summarize
from ga3ce_prep.train.schedule import warmup_cosine_lr

torch.set_num_threads(2)


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    knobs = ToyKnobs(p_missing_pose=0.1, p_no_objects=0.1)
    return open_store(write_toy_store(tmp_path_factory.mktemp("toy") / "toy.zarr", 300, seed=3, knobs=knobs))


def test_dataset_splits_and_samples(toy):
    ds = {s: ContextDataset(toy, s) for s in ("train", "val", "test")}
    assert sum(len(d) for d in ds.values()) == len(toy) == 300
    assert set(ds["train"].scene) & set(ds["test"].scene) == set()   # split by scene
    assert ds["train"].xyz is ds["test"].xyz                          # the store's objects, sorted once
    d = ds["train"]
    s = d[5]
    row = int(s["index"])
    assert s["pose"].shape == (30, 3)
    assert s["objects"].shape == (int(toy.frames["obj_count"][row]), 3)
    np.testing.assert_allclose(s["gaze"], toy.frames["gaze"][row])
    # the frame's own objects, largest mask first
    raw = toy.objects_of(row)
    area = toy.objects["area"][toy.object_slice(row)]
    np.testing.assert_array_equal(s["objects"].numpy(), raw[np.argsort(-area, kind="stable")])
    assert np.all(np.diff(s["area"].numpy()) <= 0)
    assert (d.obj_count == 0).any()  # the fixture has both cases
    assert np.isnan(d.pose).all(axis=(1, 2)).any()


def test_dataset_drops_unusable_frames_and_objects(tmp_path):
    frames, objects, scenes = toy_world(40, seed=1)
    frames["gaze"][0] = np.nan                 # unknown gaze: out of training/eval sets
    frames["view"][1] = np.nan                 # no view prior: out everywhere
    frames["head_pos"][2] = np.nan             # no head position: a valid frame with zero objects
    start3 = int(frames["obj_count"][:3].sum())
    objects["xyz"][start3] = np.nan            # one bad object of frame 3
    frames["split"][:] = 0
    w = StoreWriter(tmp_path / "s.zarr", scene_names=scenes)
    w.append_frames(frames, objects)
    from ga3ce_prep.testing.toy_store import ATTRS
    w.close(ATTRS)
    st = open_store(tmp_path / "s.zarr")
    ds = ContextDataset(st, "train")
    assert len(ds) == 38
    assert ds.n_no_gaze == 1
    assert ds.n_no_view == 1
    assert 0 not in ds.rows
    assert 1 not in ds.rows
    assert len(ContextDataset(st, "train", require_gaze=False)) == 39
    pos = {int(r): i for i, r in enumerate(ds.rows)}
    assert ds.obj_count[pos[2]] == 0
    assert ds.obj_count[pos[3]] == frames["obj_count"][3] - 1
    assert np.isfinite(ds.xyz).all()
    b = ds.batch(np.arange(len(ds)))
    assert torch.isfinite(b.objects).all()


def test_collate_matches_vectorised_batch(toy):
    ds = ContextDataset(toy, "train")
    idx = np.array([3, 0, 17, 9, 40, 41, 2])
    for n_max in (None, 12, 60):
        a = collate([ds[i] for i in idx], n_max=n_max)
        b = ds.batch(idx, n_max=n_max)
        for name in ("view", "pose", "head_pos", "gaze", "objects", "mask", "index"):
            torch.testing.assert_close(getattr(a, name), getattr(b, name), equal_nan=True)
        S = int(ds.obj_count[idx].max()) if n_max is None else n_max
        assert a.objects.shape == (7, S, 3)
        np.testing.assert_array_equal(a.mask.sum(1).numpy(), np.minimum(ds.obj_count[idx], S))
    # truncation keeps the largest masks, whatever order the samples come in
    s = ds[int(np.argmax(ds.obj_count))]
    perm = torch.randperm(len(s["objects"]), generator=torch.Generator().manual_seed(0))
    shuffled = {**s, "objects": s["objects"][perm], "area": s["area"][perm]}
    torch.testing.assert_close(collate([shuffled], n_max=5).objects[0], s["objects"][:5])
    # a DataLoader with the collate and the bucketing sampler yields the same batches
    loader = torch.utils.data.DataLoader(ds, batch_sampler=BucketBatchSampler(ds.obj_count, 16, seed=1),
                                         collate_fn=functools.partial(collate, n_max=None))
    first = next(iter(loader))
    ref = ds.batch(BucketBatchSampler(ds.obj_count, 16, seed=1).batches()[0])
    torch.testing.assert_close(first.objects, ref.objects)


def test_fixed_nmax_padding_keeps_the_prediction(toy):
    torch.manual_seed(0)
    model = GA3CE().eval()
    ds = ContextDataset(toy, "test")
    idx = np.arange(min(24, len(ds)))
    with torch.no_grad():
        outs = [model(*(lambda b: (b.view, b.pose, b.head_pos, b.objects, b.mask))(ds.batch(idx, n_max)))
                for n_max in (None, 168)]
    torch.testing.assert_close(outs[0], outs[1], atol=1e-5, rtol=0)


def test_dataset_profiles(tmp_path):
    gfie, gafa, toy = (DatasetProfile.for_dataset(n) for n in ("gfie", "gafa", "toy"))
    assert (gfie.n_max, gfie.view_noise, gfie.paper_column) == (168, True, "gfie")
    assert (gafa.n_max, gafa.view_noise, gafa.paper_column) == (278, False, "gafa")
    assert (toy.n_max, toy.view_noise, toy.paper_column) == (168, False, "gfie")   # an unknown dataset
    st = open_store(write_toy_store(tmp_path / "gafa.zarr", 40, dataset="gafa"))
    assert ContextDataset(st, "train").profile == gafa


def test_bucket_sampler():
    counts = np.random.default_rng(0).integers(0, 60, 1000)
    s = BucketBatchSampler(counts, 32, seed=4, batching="mixed")
    b0 = s.batches()
    assert np.array_equal(np.sort(np.concatenate(b0)), np.arange(1000))
    assert len(b0) == len(s) == 32
    again = BucketBatchSampler(counts, 32, seed=4, batching="mixed").batches()
    assert all(np.array_equal(x, y) for x, y in zip(b0, again))
    s.set_epoch(1)
    assert not all(np.array_equal(x, y) for x, y in zip(b0, s.batches()))

    def padding(batches):
        return sum(len(b) * counts[b].max() - counts[b].sum() for b in batches) / counts.sum()

    plain = BucketBatchSampler(counts, 32, seed=4, batching="shuffled").batches()
    tight = BucketBatchSampler(counts, 32, seed=4, batching="sorted").batches()
    assert padding(tight) < 0.1 < padding(b0) < 0.35 < padding(plain)
    ordered = BucketBatchSampler(counts, 32, shuffle=False).batches()
    assert np.all(np.diff(counts[np.concatenate(ordered)]) >= 0)
    with pytest.raises(ValueError, match="batching"):
        BucketBatchSampler(counts, 32, batching="bucketed")


def test_mixed_batches_mix_rooms():
    """40 rooms of 50 frames whose object counts differ by room (as in a synthetic world): sorted
    batches hold one or two rooms, mixed ones many, shuffled ones nearly a batch's worth."""
    rng = np.random.default_rng(1)
    room = np.repeat(np.arange(40), 50)
    counts = rng.integers(5, 80, 40)[room] + rng.integers(0, 3, len(room))

    def rooms(batching):
        return np.mean([len(np.unique(room[b])) for b in BucketBatchSampler(counts, 32, seed=0, batching=batching)
                        .batches()])

    assert rooms("sorted") < 4 < 8 < rooms("mixed") < rooms("shuffled")


def test_store_fingerprint(tmp_path):
    a = open_store(write_toy_store(tmp_path / "a.zarr", 50, seed=0))
    b = open_store(write_toy_store(tmp_path / "b.zarr", 50, seed=0))
    c = open_store(write_toy_store(tmp_path / "c.zarr", 50, seed=1))
    assert store_fingerprint(a) == store_fingerprint(b) != store_fingerprint(c)


def test_view_noise_shift():
    v = torch.nn.functional.normalize(torch.randn(20000, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    g = torch.Generator().manual_seed(1)
    out = view_noise(v, g)
    ang = angular_error_deg(out.numpy(), v.numpy())
    assert 19.0 < ang.mean() < 25.0  # about 22 degrees (docs/paper.md)
    assert ang.max() < 61.0
    np.testing.assert_allclose(out.norm(dim=-1).numpy(), 1.0, atol=1e-6)
    torch.testing.assert_close(view_noise(v, torch.Generator().manual_seed(1)), out)


def test_object_dropout_drops_the_expected_share_of_real_objects_only():
    mask = torch.zeros(400, 50, dtype=torch.bool)
    mask[:, :30] = True                                    # 30 real objects, 20 padding slots per frame
    out = object_dropout(mask, torch.Generator().manual_seed(0), 0.4)
    assert not out[:, 30:].any()                           # padding stays padding
    assert not (out & ~mask).any()
    kept = out[:, :30].float().mean().item()
    assert kept == pytest.approx(0.6, abs=0.01)            # 12,000 draws: 1 sd = 0.0045
    assert torch.equal(object_dropout(mask, torch.Generator().manual_seed(0), 0.4), out)    # seeded
    assert not torch.equal(object_dropout(mask, torch.Generator().manual_seed(1), 0.4), out)
    assert torch.equal(object_dropout(mask, torch.Generator().manual_seed(0), 0.0), mask)
    frames = object_dropout(mask, torch.Generator().manual_seed(0), 0.0, frame_p=0.25)
    hidden = ~frames[:, :30].any(1)
    assert torch.equal(frames, mask & ~hidden[:, None])    # a frame keeps all its objects or none
    assert hidden.float().mean().item() == pytest.approx(0.25, abs=0.07)   # 400 frames: 1 sd = 0.022


def test_object_jitter_has_the_set_spread():
    objects = torch.randn(200, 40, 3, generator=torch.Generator().manual_seed(2))
    out = object_jitter(objects, torch.Generator().manual_seed(3), 0.1)
    d = out - objects
    assert d.mean().abs().item() < 0.003                   # 24,000 draws: 1 sd of the mean = 0.0006
    assert d.std().item() == pytest.approx(0.1, rel=0.02)
    assert torch.equal(object_jitter(objects, torch.Generator().manual_seed(3), 0.1), out)


def test_warmup_cosine_schedule():
    lrs = [warmup_cosine_lr(s, 100, 20, 1.0) for s in range(100)]
    assert lrs[0] == pytest.approx(0.05)
    assert lrs[19] == pytest.approx(1.0)
    assert lrs[20] == pytest.approx(1.0)
    assert np.all(np.diff(lrs[:20]) > 0)
    assert np.all(np.diff(lrs[20:]) < 0)
    assert lrs[60] == pytest.approx(0.5, abs=1e-9)
    assert lrs[-1] < 1e-3


def test_baselines():
    pose = np.zeros((2, 30, 3))
    pose[:, 24] = [0, 0, 1.1]      # nose
    pose[:, 26] = [-1, 0, 0.1]     # left ear
    pose[:, 28] = [1, 0, 0.1]      # right ear
    pose[1, 26] = np.nan
    v = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    d, ok = head_direction_from_pose(pose, v)
    np.testing.assert_allclose(d, [[0, 0, 1], [0, 1, 0]])
    assert ok.tolist() == [True, False]
    # snap: v 10 degrees off object A (within a 15 degree cone), 40 degrees off B
    head = np.zeros((2, 3))
    t = np.radians(10)
    v = np.array([[np.sin(t), 0, np.cos(t)], [np.sin(np.radians(40)), 0, np.cos(np.radians(40))]])
    objs = np.array([[[0, 0, 2.0], [-2, 0, 0]], [[0, 0, 3.0], [0, 0, 0]]])
    mask = np.array([[True, True], [True, False]])
    out, snapped = snap_to_object(v, head, objs, mask, 15.0)
    np.testing.assert_allclose(out, [[0, 0, 1], v[1]])
    assert snapped.tolist() == [True, False]
    gaze = np.array([[0, 0, 1.0], [0, 0, 1.0]])
    assert choose_snap_cone(v, head, objs, mask, gaze, (5.0, 20.0, 50.0)) == 50.0


def test_metrics():
    pred = np.array([[1.0, 0, 0], [0, 1, 1], [0, 0, -1]])
    gt = np.array([[0, 1.0, 0], [0, 1, 1], [0.0, 0, -1]]) / np.array([[1], [np.sqrt(2)], [1]])
    e2 = angular_errors_2d(pred, gt)
    np.testing.assert_allclose(e2[:2], [90, 0], atol=1e-6)
    assert np.isnan(e2[2])                                   # x-y part vanishes: skipped
    r = summarize(pred, gt, np.array([0, 0, 1]), ["a", "b"])
    assert r.mae3d == pytest.approx(30, abs=1e-5)
    assert r.mae2d == pytest.approx(45, abs=1e-5)
    assert r.front.n == 2  # z <= 0 is front
    assert r.front.mae3d == pytest.approx(45, abs=1e-5)
    assert r.back.n == 1
    assert r.back.mae3d == pytest.approx(0, abs=1e-5)
    assert r.per_scene["a"].to_json() == {"n": 2, "mae3d": pytest.approx(45, abs=1e-5),
                                          "mae2d": pytest.approx(45, abs=1e-5)}
    assert r.per_scene["b"].n == 1 and np.isnan(r.per_scene["b"].mae2d)
    # front/back per window (GAFA): given, not from each frame's own ground truth
    w = summarize(pred, gt, np.array([0, 0, 1]), ["a", "b"], front=np.array([False, False, True]))
    assert (w.front.n, w.back.n) == (1, 2)
    assert w.front.mae3d == pytest.approx(0, abs=1e-5) and w.back.mae3d == pytest.approx(45, abs=1e-5)
