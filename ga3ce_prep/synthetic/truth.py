"""The truth side-car `truth.h5`: exact per-frame ground truth of a synthetic dataset, keyed by the
dataset adapters' frame ids, read by the pipeline's `oracle` backends through `TruthReader`.

Layout (N frames = truth rows, one per camera image; M = total object-table rows; camera frame,
metres; the layout is documented in docs/synthetic.md)::

    attrs: format, truth_version, width, height, seed, scenes (rooms), sessions_per_room, protocol,
           preset, config (JSON), target_kinds, object_kinds, postures, shapes (JSON lists / dicts
           naming the integer codes)
    frames/frame_id, split, scene, camera     (N,) str
    frames/K (N,3,3) f64; image_size (N,2) i32 (W, H)
    frames/pose (N,30,3) f64                  smpl+head_30, exact
    frames/eye, gaze_target, gaze, head_dir, head_center, chest_pos, chest_dir (N,3) f64
    frames/head_R (N,3,3), head_axes (N,3)    head ellipsoid axes (columns) and semi-axes
    frames/target_kind (N,) i8, target_instance (N,) i32, target_visible (N,) bool
    frames/head_box, body_box (N,4) f64 x1,y1,x2,y2 px; eye_2d, gaze_2d (N,2) f64 px
    frames/R_w2c (N,3,3), cam_center (N,3)    camera pose in the scene's world frame (z up)
    frames/posture (N,) i8, person_height (N,) f32, reaching (N,) bool, time_index (N,) i32
    frames/room, session (N,) i32              the recording: room index, session within the room
    frames/obj_start (N,) i64, obj_count (N,) i32   CSR into objects/*
    objects/instance (M,) i32, kind (M,) i8, shape (M,) i8, centroid (M,3) f64, pixels (M,) i32,
    objects/size (M,) f32
    depth (N,H,W) f32   exact rendered z, 0 = no hit; chunks (1,H,W), lzf + shuffle
    instance (N,H,W) i16 per-pixel instance id, -1 = none; chunks (1,H,W), lzf + shuffle
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path

import h5py
import numpy as np

from ..errors import DatasetFormatError
from .config import POSTURES, TARGET_KINDS
from .room import KINDS, SHAPE_CODES

TRUTH_VERSION = "1.1"  # 1.1: frames/room, frames/session and the protocol attributes
FILENAME = "truth.h5"
# attrs["protocol"]: how rooms relate to splits (generation.generate)
PROTOCOL_SEEN = "seen-rooms: {r} sessions per room, split by session"
PROTOCOL_UNSEEN = "unseen-rooms: one session per room, split by room"


def protocol_line(sessions_per_room: int) -> str:
    """The protocol line of a world recording each room in `sessions_per_room` sessions."""
    return PROTOCOL_UNSEEN if sessions_per_room == 1 else PROTOCOL_SEEN.format(r=sessions_per_room)


def world_provenance(root: str | Path) -> dict | None:
    """What a store's provenance records of the synthetic world at dataset root `root` (its
    truth.h5's attributes: format, seed, preset, rooms, sessions per room, frames per session,
    protocol), or None when the root holds no readable truth side-car."""
    path = Path(root) / FILENAME
    if not path.is_file():
        return None
    try:
        with h5py.File(path, "r") as f:
            a = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items()}
    except OSError:
        return None
    r = int(a.get("sessions_per_room", 1))
    return {"format": str(a.get("format", "")), "seed": int(a.get("seed", 0)), "preset": str(a.get("preset", "")),
            "rooms": int(a.get("scenes", 0)), "sessions_per_room": r,
            "frames_per_session": int(a.get("frames_per_scene", 0)),
            "protocol": str(a.get("protocol", protocol_line(r))), "truth_version": str(a.get("truth_version", ""))}


@dataclass
class ObjectTable:
    """One frame's instances: id, kind code (room.KINDS), shape code (room.SHAPE_CODES),
    camera-frame centroid (M, 3), visible pixels (M,), largest extent (M,) metres."""

    instance: np.ndarray
    kind: np.ndarray
    shape: np.ndarray
    centroid: np.ndarray
    pixels: np.ndarray
    size: np.ndarray


@dataclass
class TruthFrame:
    """One frame's exact truth, camera frame, metres. Codes: target_kind in TARGET_KINDS order
    (0 object, 1 space, 2 out_of_view); posture in POSTURES order."""

    frame_id: str
    split: str
    scene: str
    camera: str
    K: np.ndarray                # (3, 3)
    image_size: np.ndarray       # (2,) W, H
    pose: np.ndarray             # (30, 3)
    eye: np.ndarray              # (3,)
    gaze_target: np.ndarray      # (3,)
    gaze: np.ndarray             # (3,) unit
    head_dir: np.ndarray         # (3,) unit
    head_center: np.ndarray      # (3,)
    chest_pos: np.ndarray        # (3,)
    chest_dir: np.ndarray        # (3,) unit
    head_R: np.ndarray           # (3, 3)
    head_axes: np.ndarray        # (3,)
    target_kind: int
    target_instance: int
    target_visible: bool
    head_box: np.ndarray         # (4,)
    body_box: np.ndarray         # (4,)
    eye_2d: np.ndarray           # (2,)
    gaze_2d: np.ndarray          # (2,)
    R_w2c: np.ndarray            # (3, 3)
    cam_center: np.ndarray       # (3,)
    posture: int
    person_height: float
    reaching: bool
    time_index: int
    room: int                    # room index (0..scenes-1)
    session: int                 # session within the room (0..sessions_per_room-1)
    objects: ObjectTable
    depth: np.ndarray | None = field(default=None, repr=False)     # (H, W) float32
    instance: np.ndarray | None = field(default=None, repr=False)  # (H, W) int16


_STR = ("frame_id", "split", "scene", "camera")
_SCALAR = {"target_kind": np.int8, "target_instance": np.int32, "target_visible": bool, "posture": np.int8,
           "person_height": np.float32, "reaching": bool, "time_index": np.int32, "room": np.int32,
           "session": np.int32}
_INT_ARR = {"image_size": np.int32}
_SKIP = ("objects", "depth", "instance")
_OBJ = {"instance": np.int32, "kind": np.int8, "shape": np.int8, "centroid": np.float64, "pixels": np.int32,
        "size": np.float32}


def _vector_fields() -> list[str]:
    return [f.name for f in fields(TruthFrame) if f.name not in _STR + _SKIP and f.name not in _SCALAR]


class TruthWriter:
    """Appends TruthFrames to `path` (an HDF5 file); small arrays are written on close."""

    def __init__(self, path: str | Path, width: int, height: int, attrs: dict):
        self.path = Path(path)
        self.f = h5py.File(self.path, "w")
        self.W, self.H = width, height
        # lzf (bundled with h5py): 40% less writing time than gzip 1 for 20% larger files
        kw = dict(chunks=(1, height, width), compression="lzf", shuffle=True)
        self.depth = self.f.create_dataset("depth", (0, height, width), np.float32,
                                           maxshape=(None, height, width), **kw)
        self.instance = self.f.create_dataset("instance", (0, height, width), np.int16, maxshape=(None, height, width),
                                              fillvalue=-1, **kw)
        base = {"format": "", "truth_version": TRUTH_VERSION, "width": width, "height": height,
                "target_kinds": json.dumps(list(TARGET_KINDS)), "object_kinds": json.dumps(list(KINDS)),
                "postures": json.dumps(list(POSTURES)), "shapes": json.dumps(SHAPE_CODES)}
        base.update(attrs)
        for k, v in base.items():
            self.f.attrs[k] = v
        self.rows: list[TruthFrame] = []
        self.ids: set[str] = set()

    def add(self, fr: TruthFrame) -> None:
        if fr.frame_id in self.ids:
            raise ValueError(f"duplicate truth frame id {fr.frame_id!r}")
        self.ids.add(fr.frame_id)
        n = len(self.rows)
        self.depth.resize(n + 1, axis=0)
        self.instance.resize(n + 1, axis=0)
        self.depth[n] = fr.depth
        self.instance[n] = fr.instance
        self.rows.append(TruthFrame(**{f.name: getattr(fr, f.name) for f in fields(TruthFrame)
                                       if f.name not in ("depth", "instance")}))

    def close(self) -> None:
        if self.f is None:
            return
        rows, g = self.rows, self.f.require_group("frames")
        str_dt = h5py.string_dtype()
        for name in _STR:
            g.create_dataset(name, data=np.array([getattr(r, name) for r in rows], dtype=object), dtype=str_dt)
        for name, dt in _SCALAR.items():
            g.create_dataset(name, data=np.array([getattr(r, name) for r in rows], dtype=dt))
        for name in _vector_fields():
            dt = _INT_ARR.get(name, np.float64)
            data = np.stack([np.asarray(getattr(r, name), dt) for r in rows]) if rows else np.zeros((0,), dt)
            g.create_dataset(name, data=data)
        counts = np.array([len(r.objects.instance) for r in rows], np.int32)
        g.create_dataset("obj_count", data=counts)
        g.create_dataset("obj_start", data=np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
                         if rows else np.zeros(0, np.int64))
        og = self.f.require_group("objects")
        for name, dt in _OBJ.items():
            parts = [np.asarray(getattr(r.objects, name), dt) for r in rows]
            shape = (0, 3) if name == "centroid" else (0,)
            og.create_dataset(name, data=np.concatenate(parts) if parts else np.zeros(shape, dt))
        self.f.close()
        self.f = None

    def __enter__(self) -> TruthWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class TruthReader:
    """Read `truth.h5`: `TruthReader(path)`, `.frame_ids`, `.index(frame_id)`,
    `.get(frame_id) -> TruthFrame`, vectorised per-frame arrays (`.pose`, `.eye`, `.gaze`, ...
    or `.array(name)`), `.depth(frame_id)`, `.instance(frame_id)`, `.objects(frame_id)`.

    Per-frame vectors and the object table are loaded into memory on open (a few KB per frame);
    depth and instance maps are read per frame on demand.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if self.path.is_dir():
            self.path = self.path / FILENAME
        if not self.path.is_file():
            raise DatasetFormatError(f"truth side-car {self.path} not found: synthetic datasets carry it at their root "
                                     f"(regenerate with `ga3ce-prep synth`)")
        try:
            self.f = h5py.File(self.path, "r")
        except OSError as e:
            raise DatasetFormatError(f"cannot open truth side-car {self.path}: {e}") from e
        ver = str(self.f.attrs.get("truth_version", "?"))
        if ver.split(".")[0] != TRUTH_VERSION.split(".")[0]:
            raise DatasetFormatError(f"{self.path} has truth_version {ver}; this reader reads {TRUTH_VERSION}: "
                                     f"regenerate the dataset with this version of `ga3ce-prep synth`")
        self.attrs = {k: (v.item() if hasattr(v, "item") else v) for k, v in self.f.attrs.items()}
        g = self.f["frames"]
        self._arrays: dict[str, np.ndarray] = {}
        for name in g:
            a = g[name][()]
            if name in _STR:
                a = np.array([x.decode() if isinstance(x, bytes) else str(x) for x in a], dtype=object)
            self._arrays[name] = a
        self._objects = {name: self.f["objects"][name][()] for name in self.f["objects"]}
        if "room" not in self._arrays:  # truth 1.0: one session per room, a room per scene
            self._arrays["room"] = np.unique(self._arrays["scene"], return_inverse=True)[1].astype(np.int32)
            self._arrays["session"] = np.zeros(len(self._arrays["room"]), np.int32)
        self.frame_ids: list[str] = list(self._arrays["frame_id"])
        self._index = {fid: i for i, fid in enumerate(self.frame_ids)}
        self.target_kinds = tuple(json.loads(self.attrs["target_kinds"]))
        self.object_kinds = tuple(json.loads(self.attrs["object_kinds"]))

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def sessions_per_room(self) -> int:
        """Sessions recorded in each room (1: every room is one scene in one split)."""
        return int(self.attrs.get("sessions_per_room", 1))

    @property
    def protocol(self) -> str:
        """attrs["protocol"]: seen rooms (split by session) or unseen rooms (split by room)."""
        return str(self.attrs.get("protocol", protocol_line(self.sessions_per_room)))

    def index(self, frame_id: str) -> int:
        """Row of `frame_id`; KeyError naming the file when it is not there."""
        try:
            return self._index[frame_id]
        except KeyError:
            raise KeyError(f"frame {frame_id!r} is not in {self.path} ({len(self)} frames, e.g. "
                           f"{self.frame_ids[:1]}): the dataset and its truth side-car do not match") from None

    def array(self, name: str) -> np.ndarray:
        """All frames' values of one per-frame field (N, ...), in frame_ids order."""
        return self._arrays[name]

    def __getattr__(self, name: str) -> np.ndarray:
        arrays = self.__dict__.get("_arrays", {})
        if name in arrays:
            return arrays[name]
        raise AttributeError(name)

    def _row(self, key: str | int) -> int:
        return key if isinstance(key, (int, np.integer)) else self.index(key)

    def depth(self, key: str | int) -> np.ndarray:
        """(H, W) float32 exact depth (m), 0 = no hit."""
        return self.f["depth"][self._row(key)]

    def instance(self, key: str | int) -> np.ndarray:
        """(H, W) int16 instance ids, -1 = none."""
        return self.f["instance"][self._row(key)]

    def objects(self, key: str | int) -> ObjectTable:
        i = self._row(key)
        s, c = int(self._arrays["obj_start"][i]), int(self._arrays["obj_count"][i])
        return ObjectTable(**{k: v[s:s + c] for k, v in self._objects.items()})

    def get(self, key: str | int, maps: bool = True) -> TruthFrame:
        """One frame's truth; with maps=False the depth and instance maps are not read."""
        i = self._row(key)
        kw = {}
        for f in fields(TruthFrame):
            if f.name in _SKIP:
                continue
            v = self._arrays[f.name][i]
            if f.name in _SCALAR:
                v = v.item()
            kw[f.name] = v
        return TruthFrame(**kw, objects=self.objects(i), depth=self.depth(i) if maps else None,
                          instance=self.instance(i) if maps else None)

    def close(self) -> None:
        self.f.close()

    def __enter__(self) -> TruthReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
