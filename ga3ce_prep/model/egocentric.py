"""GA3CE's egocentric transform: pose normalisation and the rotation of the 3D context into the
frame where the view prior is z (docs/paper.md).

    t_pose = mean of the head joints 24..29,  s = 1 / ||J_a - J_b||  (HEAD_WIDTH_PAIR, the paper's
    "head width"),  v' = R v = z,  P'_pose = s R (P_pose - t_pose),  P'_obj = R (P_obj - t_object)

Only GA3CE's 15 joints (skeleton.GA3CE_JOINTS) are kept. Torch, batched; camera frame, metres.

Missing pose policy: joints that are NaN in the store stay NaN here and are flagged invalid; the
pose encoder gives every invalid joint a learned "missing joint" embedding. If t_pose or s cannot be
computed (no finite head joint, or either joint of the head-width pair missing) the whole pose is
invalid for that frame, and so is every joint.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..skeleton import GA3CE_JOINTS, HEAD_JOINTS, HEAD_WIDTH_PAIR
from .rotation import rotation


@dataclass
class EgocentricContext:
    """The 3D context in the egocentric frame, for a batch of B frames with S object slots.

    R: (B, 3, 3) rotation, R v = z. view: (B, 3) v' = R v (unit). pose: (B, J, 3) P'_pose in head
    widths (J = len(GA3CE_JOINTS)); invalid joints are 0. joint_valid: (B, J) bool.
    objects: (B, S, 3) P'_obj in metres (padding slots are 0).
    """

    R: torch.Tensor
    view: torch.Tensor
    pose: torch.Tensor
    joint_valid: torch.Tensor
    objects: torch.Tensor


def pose_normalization(pose: torch.Tensor, head_width_pair: tuple[int, int] = HEAD_WIDTH_PAIR,
                       head_joints: tuple[int, ...] = HEAD_JOINTS) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """GA3CE's pose origin and scale.

    pose: (B, 30, 3) metres, NaN rows = missing joints. Returns t_pose (B, 3) = mean of the finite
    head joints (0 where none), s (B,) = 1 / ||J_a - J_b|| in 1/metres (0 where undefined), and
    ok (B,) bool: both are defined and the head width is above 1 mm.
    """
    head = pose[:, list(head_joints)]                                  # (B, 6, 3)
    finite = torch.isfinite(head).all(-1)                              # (B, 6)
    n = finite.sum(-1)
    t_pose = torch.where(finite[..., None], head, torch.zeros_like(head)).sum(1) / n.clamp_min(1)[:, None]
    a, b = head_width_pair
    width = torch.linalg.vector_norm(pose[:, a] - pose[:, b], dim=-1)  # NaN if either is missing
    ok = (n > 0) & torch.isfinite(width) & (width > 1e-3)
    s = torch.where(ok, 1.0 / torch.where(ok, width, torch.ones_like(width)), torch.zeros_like(width))
    return t_pose, s, ok


def egocentric_transform(view: torch.Tensor, pose: torch.Tensor, objects: torch.Tensor,
                         head_pos: torch.Tensor, rotation_name: str = "cyclotorsion",
                         head_width_pair: tuple[int, int] = HEAD_WIDTH_PAIR) -> EgocentricContext:
    """Move a batch's 3D context into the egocentric frame.

    view: (B, 3) view prior v (unit). pose: (B, 30, 3) metres, NaN rows = missing. objects: (B, S, 3)
    metres (padding slots may hold anything finite). head_pos: (B, 3) t_object, metres.
    rotation_name: "cyclotorsion" (GA3CE), "axis_angle" (no-cyclotorsion ablation) or "none" (no
    egocentric rotation: translation and scale only). Returns an EgocentricContext.
    """
    R = rotation(rotation_name, view)                                  # (B, 3, 3)
    v_ego = torch.einsum("bij,bj->bi", R, view)
    t_pose, s, ok = pose_normalization(pose, head_width_pair)
    joints = pose[:, list(GA3CE_JOINTS)]                               # (B, 15, 3)
    joint_valid = torch.isfinite(joints).all(-1) & ok[:, None]
    centred = torch.where(joint_valid[..., None], joints - t_pose[:, None], torch.zeros_like(joints))
    pose_ego = s[:, None, None] * torch.einsum("bij,bkj->bki", R, centred)
    obj_ego = torch.einsum("bij,bkj->bki", R, objects - head_pos[:, None])
    return EgocentricContext(R=R, view=v_ego, pose=pose_ego, joint_valid=joint_valid, objects=obj_ego)
