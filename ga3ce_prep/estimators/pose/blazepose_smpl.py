"""BlazePose's 33 landmarks -> the smpl+head_30 skeleton (skeleton.JOINT_NAMES, huge8 order).

Joints BlazePose has are copied (`DIRECT`). The SMPL trunk joints it lacks are placed on the
hip-centre -> shoulder-centre axis, the neck on the shoulder-centre -> ear-centre axis, and the
collars between the shoulders, at the fractions of the project's
rest skeleton (synthetic/person.py `REST`, SMPL-like proportions: hips at 0.90 m, shoulders at
1.43 m for a 1.75 m person), the SMPL head joint halfway from the neck to the ear midpoint (REST:
0.5 cm off), and the head top above the ear midpoint along the head's up axis (REST: 1.8 cm off).
Every formula is in `DERIVED` and docs/models/pose.md, "The mapping to smpl+head_30";
`tests/test_blazepose.py` checks them against REST. A joint whose landmarks' visibility (the lowest,
for a derived joint) is below `min_visibility` is NaN: GA3CE's missing-joint embedding takes over.

Known differences from a MeTRAbs-style smpl+head_30 estimate: BlazePose's hip landmarks lie
wider apart than SMPL's hip joints (astronaut: 0.21-0.24 m; REST 0.17 m); its foot index is the
toe tip, SMPL's foot joint the toe base, a few centimetres behind; the head top is a fixed height
above the ears (`head_top_height`), not a measured point.
"""
from __future__ import annotations

import numpy as np

from ...geometry import normalize
from ...skeleton import JOINT_NAMES, N_JOINTS
from .blazepose import L

# smpl+head_30 joint -> BlazePose landmark, copied as they are.
DIRECT: dict[str, str] = {
    "lhip_smpl": "left_hip", "rhip_smpl": "right_hip", "lkne_smpl": "left_knee", "rkne_smpl": "right_knee",
    "lank_smpl": "left_ankle", "rank_smpl": "right_ankle", "ltoe_smpl": "left_foot_index",
    "rtoe_smpl": "right_foot_index", "lsho_smpl": "left_shoulder", "rsho_smpl": "right_shoulder",
    "lelb_smpl": "left_elbow", "relb_smpl": "right_elbow", "lwri_smpl": "left_wrist", "rwri_smpl": "right_wrist",
    "nose_coco": "nose", "leye_coco": "left_eye", "lear_coco": "left_ear", "reye_coco": "right_eye",
    "rear_coco": "right_ear",
}
# Fractions of the trunk vector (hip centre -> shoulder centre) above the hip centre, from REST.
TRUNK_FRACTION: dict[str, float] = {"pelv_smpl": 0.11, "bell_smpl": 0.32, "spin_smpl": 0.57, "thor_smpl": 0.72}
# neck = shoulder centre + 0.25 (ear centre - shoulder centre), REST 0.05 / 0.20 m: the neck follows the head,
# not the trunk, and needs no hips (often unseen in gaze datasets).
NECK_FRACTION = 0.25
COLLAR_FRACTION = 0.42  # collar = shoulder centre + 0.42 (shoulder - shoulder centre), REST 0.075 / 0.18 m
# The derived joints' formulas, as docs/models/pose.md ("The mapping to smpl+head_30") lists them.
DERIVED: dict[str, str] = {
    **{j: f"hip_c + {f} (sho_c - hip_c)" for j, f in TRUNK_FRACTION.items()},
    "lcla_smpl": f"sho_c + {COLLAR_FRACTION} (left_shoulder - sho_c)",
    "rcla_smpl": f"sho_c + {COLLAR_FRACTION} (right_shoulder - sho_c)",
    "neck_smpl": f"sho_c + {NECK_FRACTION} (ear_c - sho_c)",
    "head_smpl": "(neck + ear_c) / 2",
    "lhan_smpl": "(left_pinky + left_index) / 2  (the knuckles)",
    "rhan_smpl": "(right_pinky + right_index) / 2",
    "htop_mpi_inf_3dhp": "ear_c + head_top_height * unit(cross(eye_c - ear_c, left_ear - right_ear))",
}
_J = {name: i for i, name in enumerate(JOINT_NAMES)}


def _mid(p: np.ndarray, v: np.ndarray, a: str, b: str) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint of landmarks a and b and its visibility (the lower one)."""
    return 0.5 * (p[L[a]] + p[L[b]]), min(v[L[a]], v[L[b]])


def to_smpl_head30(world: np.ndarray, visibility: np.ndarray, min_visibility: float = 0.5,
                   head_top_height: float = 0.12) -> np.ndarray:
    """The 30 smpl+head_30 joints (30, 3) from BlazePose landmarks.

    world: (33, 3) metres, any frame (camera frame for the pose stage); visibility: (33,) in [0, 1].
    min_visibility: joints whose (lowest) landmark visibility is below it are NaN.
    head_top_height: metres from the ear midpoint up to the head top (REST 0.12; adult
    tragion-to-vertex heights are 0.12-0.13 m).
    """
    p, v = np.asarray(world, np.float64), np.asarray(visibility, np.float64)
    out = np.full((N_JOINTS, 3), np.nan)
    vis = np.zeros(N_JOINTS)
    for j, lm in DIRECT.items():
        out[_J[j]], vis[_J[j]] = p[L[lm]], v[L[lm]]
    hip_c, v_hip = _mid(p, v, "left_hip", "right_hip")
    sho_c, v_sho = _mid(p, v, "left_shoulder", "right_shoulder")
    for j, f in TRUNK_FRACTION.items():
        out[_J[j]], vis[_J[j]] = hip_c + f * (sho_c - hip_c), min(v_hip, v_sho)
    for side in ("left", "right"):
        s = f"{side}_shoulder"
        out[_J[f"{side[0]}cla_smpl"]] = sho_c + COLLAR_FRACTION * (p[L[s]] - sho_c)
        vis[_J[f"{side[0]}cla_smpl"]] = v_sho
        out[_J[f"{side[0]}han_smpl"]], vis[_J[f"{side[0]}han_smpl"]] = _mid(p, v, f"{side}_pinky", f"{side}_index")
    ear_c, v_ear = _mid(p, v, "left_ear", "right_ear")
    eye_c, v_eye = _mid(p, v, "left_eye", "right_eye")
    neck = sho_c + NECK_FRACTION * (ear_c - sho_c)
    out[_J["neck_smpl"]] = neck
    out[_J["head_smpl"]] = 0.5 * (neck + ear_c)
    vis[_J["neck_smpl"]] = vis[_J["head_smpl"]] = min(v_sho, v_ear)
    up = np.cross(eye_c - ear_c, p[L["left_ear"]] - p[L["right_ear"]])
    out[_J["htop_mpi_inf_3dhp"]] = ear_c + head_top_height * normalize(up) if np.linalg.norm(up) > 1e-9 else np.nan
    vis[_J["htop_mpi_inf_3dhp"]] = min(v_ear, v_eye)
    out[~(vis >= min_visibility)] = np.nan
    return out


__all__ = ["COLLAR_FRACTION", "DERIVED", "DIRECT", "NECK_FRACTION", "TRUNK_FRACTION", "to_smpl_head30"]
