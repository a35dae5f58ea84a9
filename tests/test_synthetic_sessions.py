"""Rooms recorded in several sessions (`sessions_per_room`) and the transfer preset: truth room and
session ids, splits by session with every val/test room seen in training, one layout per room,
each format's conventions (GFIE folders, GAFA's session split, CAD-120 all test), the preset's
camera, and the protocol in the dataset's provenance."""
import math
import shutil

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from ga3ce_prep.datasets import gafa, gfie, open_dataset
from ga3ce_prep.errors import ConfigError
from ga3ce_prep.synthetic import generate
from ga3ce_prep.synthetic.camera import intrinsics
from ga3ce_prep.synthetic.cli import synth
from ga3ce_prep.synthetic.config import load_config, load_preset, preset_names
from ga3ce_prep.synthetic.room import build_room
from ga3ce_prep.synthetic.stats import split_recordings
from ga3ce_prep.synthetic.truth import PROTOCOL_UNSEEN, TruthReader, world_provenance
from ga3ce_prep.synthetic.world import Scene, SceneError
from ga3ce_prep.synthetic.writers import assign_session_splits, assign_splits

W, H = 96, 72
ROOMS, R, F = 4, 3, 2


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("sessions") / "gfie"
    generate("gfie", root, scenes=ROOMS, frames_per_scene=F, seed=13, width=W, height=H, progress=False,
             sessions_per_room=R)
    return root


def _world_centroids(tr: TruthReader, i: int) -> np.ndarray:
    """Frame i's room instances (not the person: the last row) as world-frame centroids (M, 3)."""
    c = tr.objects(i).centroid[:-1]
    return c @ tr.R_w2c[i] + tr.cam_center[i]  # X_w = R^T X_c + C, row-wise


def test_truth_records_room_and_session(world):
    with TruthReader(world) as tr:
        assert tr.sessions_per_room == R
        assert tr.protocol == "seen-rooms: 3 sessions per room, split by session"
        assert tr.attrs["scenes"] == ROOMS
        pairs = list(zip(tr.room.tolist(), tr.session.tolist()))
        assert sorted(set(pairs)) == [(i, j) for i in range(ROOMS) for j in range(R)]
        assert all(pairs.count(p) == F for p in set(pairs))
        # one GFIE scene folder per session
        assert len(set(tr.scene.tolist())) == ROOMS * R
        f = tr.get(tr.frame_ids[-1], maps=False)
        assert (f.room, f.session) == (ROOMS - 1, R - 1)


def test_val_and_test_rooms_have_training_sessions(world):
    with TruthReader(world) as tr:
        room, session, split = tr.room, tr.session, tr.split
        train_rooms = set(room[split == "train"].tolist())
        assert train_rooms == set(range(ROOMS))
        assert set(split[session == 0].tolist()) == {"train"}
        for name in ("val", "test"):
            assert set(room[split == name].tolist()) <= train_rooms
        c = split_recordings(tr)
        # 12 sessions: round(0.15 * 12) = 2 each for val and test
        assert {k: v["sessions"] for k, v in c.items()} == {"train": 8, "val": 2, "test": 2}
        assert all(v["rooms_seen_in_training"] == v["rooms"] for v in c.values())


def test_sessions_share_the_room_and_differ_in_person_or_camera(world):
    with TruthReader(world) as tr:
        first = {}
        for i in range(len(tr)):
            key = int(tr.room[i])
            cen = _world_centroids(tr, i)
            if key not in first:
                first[key] = (i, cen)
                continue
            j, ref = first[key]
            assert cen.shape == ref.shape  # the same instances
            np.testing.assert_allclose(cen, ref, atol=1e-6)
            if tr.session[i] != tr.session[j]:
                assert (tr.person_height[i] != tr.person_height[j]
                        or not np.allclose(tr.cam_center[i], tr.cam_center[j]))
        # and rooms differ from each other
        assert first[0][1].shape != first[1][1].shape or not np.allclose(first[0][1], first[1][1])


def test_gfie_folders_per_split(world):
    with TruthReader(world) as tr:
        for name, folder in ((s, f) for f, s in gfie.SPLIT_FOLDERS.items()):
            scenes = sorted(p.name for p in (world / "rgb" / folder).iterdir())
            n = len(set(tr.scene[tr.split == name].tolist()))
            assert scenes == sorted(f"scene{k}" for k in range(1, n + 1))
            assert len((world / f"{folder}_annotation.txt").read_text().splitlines()) == 1 + n * F
    frames = list(open_dataset("gfie", world).frames())
    assert len(frames) == ROOMS * R * F


def test_assign_session_splits():
    for rooms, r in ((1, 2), (3, 2), (4, 3), (10, 4), (48, 4)):
        s = assign_session_splits(rooms, r, seed=5)
        n = rooms * r
        assert s == assign_session_splits(rooms, r, seed=5)
        assert len(s) == n
        assert all(s[i * r] == "train" for i in range(rooms))
        for name in ("val", "test"):
            for k in (k for k, x in enumerate(s) if x == name):
                assert any(s[(k // r) * r + j] == "train" for j in range(r))
        if n >= 12:
            assert s.count("test") == s.count("val") == round(0.15 * n)
    assert assign_session_splits(1, 2, 0) == ["train", "test"]
    assert assign_session_splits(48, 4, 1) != assign_session_splits(48, 4, 2)
    assert assign_session_splits(5, 1, 3) == assign_splits(5, 3)  # one session per room: by room


def test_a_room_without_a_placement_names_the_knob():
    cfg = load_config("gfie", overrides={"camera": {"distance": [40.0, 50.0]}})
    room = build_room(cfg, np.random.default_rng(0), sitting=True)
    with pytest.raises(SceneError, match="camera.distance"):
        Scene("gfie", cfg, intrinsics(cfg.camera, W, H), W, H, np.random.default_rng(1), room=room)


def test_gafa_sessions_follow_gafas_split(tmp_path):
    root = tmp_path / "gafa"
    generate("gafa", root, scenes=2, frames_per_scene=2, seed=3, width=W, progress=False, sessions_per_room=2)
    with TruthReader(root) as tr:
        for room in range(2):
            env = gafa.SCENES[room]
            names = set(tr.scene[tr.room == room].tolist())
            assert len(names) == 2 and all(n.split("/")[0] == env for n in names)
            assert {gafa.session_split(n) for n in names} == {"train", "test"}
        for name, split in zip(tr.scene, tr.split):
            assert split == gafa.session_split(name)
    frames = list(open_dataset("gafa", root).frames())
    assert {f.split for f in frames} == {"train", "test"}


def test_transfer_preset_camera_and_world(tmp_path):
    assert "transfer" in preset_names()
    pr = load_preset("transfer")
    assert pr.format == "cad120" and pr.seed_offset > 0
    K0 = intrinsics(load_config("gfie").camera, 640, 480)
    K1 = intrinsics(load_config("cad120", preset="transfer").camera, 640, 480)
    ratio = math.tan(math.radians(45)) / math.tan(math.radians(31))  # GFIE's ~90 deg vs CAD-120's ~62 deg
    np.testing.assert_allclose(K1[0, 0] / K0[0, 0], ratio, rtol=1e-5)
    np.testing.assert_allclose(K1[1, 1] / K0[1, 1], ratio, rtol=1e-5)
    np.testing.assert_array_equal(K1[:2, 2], K0[:2, 2])
    with pytest.raises(ConfigError, match="cad120"):
        load_config("gfie", preset="transfer")
    with pytest.raises(ConfigError, match="known presets: .*transfer"):
        load_preset("nosuch")
    out = tmp_path / "transfer"
    generate("cad120", out, scenes=2, frames_per_scene=2, seed=0, width=W, height=H, progress=False,
             sessions_per_room=2, preset="transfer")
    cam = np.load(out / "CameraKinect.npy")
    np.testing.assert_allclose(cam[0] / (525.0 * W / 640), ratio, rtol=1e-5)
    with TruthReader(out) as tr:
        assert tr.attrs["seed"] == pr.seed_offset and tr.attrs["preset"] == "transfer"
        assert set(tr.split.tolist()) == {"test"}  # CAD-120 is an evaluation set
        assert len(set(tr.scene.tolist())) == 4  # one dataset id per session
        assert ((tr.cam_center[:, 2] >= 0.9) & (tr.cam_center[:, 2] <= 1.8)).all()
    frames = list(open_dataset("cad120", out).frames())
    assert len(frames) == 8


def test_synth_command_presets_and_sessions(tmp_path):
    r = CliRunner().invoke(synth, ["--help"])
    assert r.exit_code == 0
    assert "--sessions-per-room" in r.output and "--preset [transfer]" in r.output
    r = CliRunner().invoke(synth, ["--preset", "transfer", "--format", "gfie", "--out", str(tmp_path / "x")])
    assert r.exit_code != 0 and "cad120" in r.output
    r = CliRunner().invoke(synth, ["--preset", "nosuch", "--out", str(tmp_path / "x")])
    assert r.exit_code != 0 and "transfer" in r.output
    out = tmp_path / "g"
    r = CliRunner().invoke(synth, ["--out", str(out), "--scenes", "2", "--sessions-per-room", "2",
                                   "--frames-per-scene", "1", "--width", str(W), "--height", str(H), "--quiet"])
    assert r.exit_code == 0, r.output
    assert "protocol: seen-rooms: 2 sessions per room, split by session" in r.output
    assert "train    2 sessions in    2 rooms" in r.output


def test_provenance_records_the_protocol(world, tmp_path):
    p = world_provenance(world)  # what run_pipeline records as the store's dataset.synthetic
    assert p["protocol"].startswith("seen-rooms") and p["sessions_per_room"] == R
    assert (p["seed"], p["rooms"], p["frames_per_session"]) == (13, ROOMS, F)
    # a 1.0 side-car (no room/session datasets): one session per room, rooms by scene
    old = tmp_path / "old"
    shutil.copytree(world, old)
    with h5py.File(old / "truth.h5", "a") as f:
        del f["frames/room"], f["frames/session"]
        for k in ("sessions_per_room", "protocol"):
            del f.attrs[k]
        f.attrs["truth_version"] = "1.0"
    with TruthReader(old) as tr:
        assert tr.protocol == PROTOCOL_UNSEEN
        assert len(set(tr.room.tolist())) == ROOMS * R and not tr.session.any()
