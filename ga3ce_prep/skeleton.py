"""The smpl+head_30 skeleton (MeTRAbs/NLF 2023 "28-dataset" models, huge8 joint order) and the
OpenPose BODY_25 layout GAFA's 2D keypoints use. Where the order comes from: docs/paper.md §2.

Select joints of a real estimator's output by name (`JOINT_NAMES`), never by index: the 2021
models order the face joints differently.
"""
from __future__ import annotations

import numpy as np

from .geometry import normalize

JOINT_NAMES: tuple[str, ...] = (
    "pelv_smpl", "lhip_smpl", "rhip_smpl", "bell_smpl", "lkne_smpl", "rkne_smpl", "spin_smpl",
    "lank_smpl", "rank_smpl", "thor_smpl", "ltoe_smpl", "rtoe_smpl", "neck_smpl", "lcla_smpl",
    "rcla_smpl", "head_smpl", "lsho_smpl", "rsho_smpl", "lelb_smpl", "relb_smpl", "lwri_smpl",
    "rwri_smpl", "lhan_smpl", "rhan_smpl",
    "nose_coco", "leye_coco", "lear_coco", "reye_coco", "rear_coco", "htop_mpi_inf_3dhp",
)
N_JOINTS = len(JOINT_NAMES)  # 30
J = {name.split("_")[0]: i for i, name in enumerate(JOINT_NAMES)}  # short names: J["nose"] == 24

# Parent of each joint (kinematic tree used by the synthetic world); -1 for the root.
PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
    15, 15, 15, 15, 15, 15,
)
# The skeleton's bones: (joint, its parent) for every joint but the root.
BONES: tuple[tuple[int, int], ...] = tuple((j, p) for j, p in enumerate(PARENTS) if p >= 0)

HEAD_JOINTS: tuple[int, ...] = (24, 25, 26, 27, 28, 29)  # t_pose = mean of these (GA3CE)
# GA3CE's 15-joint subset: pelvis, knees, spine2, ankles, neck, elbows, wrists, nose, ears, head top.
GA3CE_JOINTS: tuple[int, ...] = (0, 4, 5, 6, 7, 8, 12, 18, 19, 20, 21, 24, 26, 28, 29)
# The paper's "head width" pair, s = 1 / ||J24 - J28||. In the huge8 order this is nose to right
# ear (about 0.1 m), not ear to ear (26, 28): we keep the paper's pair as the default.
HEAD_WIDTH_PAIR: tuple[int, int] = (24, 28)

BODY25_NAMES: tuple[str, ...] = (
    "Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "MidHip",
    "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
    "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel",
)
# For each BODY_25 joint, the smpl+head_30 joint that stands for it (toes and heels share the
# SMPL foot/ankle joints; MidHip is the SMPL pelvis).
BODY25_FROM_SMPL30: tuple[int, ...] = (
    24, 12, 17, 19, 21, 16, 18, 20, 0, 2, 5, 8, 1, 4, 7, 27, 25, 28, 26,
    10, 10, 7, 11, 11, 8,
)
BODY25_HEAD: tuple[int, ...] = (0, 1, 15, 16, 17, 18)  # GAFA's head joints (nose, neck, eyes, ears)


def head_direction_from_pose(pose: np.ndarray, fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """normalise(nose - (left ear + right ear) / 2) from smpl+head_30 poses (n, 30, 3).

    Frames missing the nose or an ear take `fallback` (n, 3) (pass v). Returns (directions (n, 3),
    ok (n,) bool: the pose gave the direction)."""
    nose, lear, rear = pose[:, J["nose"]], pose[:, J["lear"]], pose[:, J["rear"]]
    d = nose - 0.5 * (lear + rear)
    ok = np.isfinite(d).all(1) & (np.linalg.norm(np.nan_to_num(d), axis=1) > 1e-6)
    out = np.where(ok[:, None], normalize(np.nan_to_num(d)), fallback)
    return out, ok
