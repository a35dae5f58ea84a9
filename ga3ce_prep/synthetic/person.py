"""The person: the smpl+head_30 skeleton (skeleton.JOINT_NAMES order) posed by forward kinematics
from a rest skeleton scaled by height, and a body mesh (limbs as cylinders, joints as balls, torso
and head as ellipsoids) so the head has depth and the person occludes things.

Body frame: x forward, y left, z up, metres, origin on the floor under the pelvis. The face joints
(24 nose, 25 leye, 26 lear, 27 reye, 28 rear, 29 head top) lie on the head ellipsoid's surface and
turn with the head. A joint's local rotation L[j] turns the bones below it:
p[c] = p[j] + G[j] @ (rest[c] - rest[j]) with G[j] = G[parent(j)] @ L[j].
"""
from __future__ import annotations

import colorsys
from dataclasses import dataclass

import cv2
import numpy as np

from .. import skeleton
from . import meshes
from .meshes import cross3

PARENTS = np.array(skeleton.PARENTS)
REF_HEIGHT = 1.75
HEAD_CENTRE = np.array([0.02, 0.0, 1.635])       # head ellipsoid centre (rest, 1.75 m)
HEAD_AXES = np.array([0.10, 0.078, 0.115])       # semi-axes: front-back, left-right, up-down


def _on_head(y: float, z: float, side: float = 1.0) -> np.ndarray:
    """Point of the head ellipsoid's front (side=1) or back surface at lateral y and height z."""
    a, b, c = HEAD_AXES
    x = a * np.sqrt(max(0.0, 1 - (y / b) ** 2 - (z / c) ** 2))
    return HEAD_CENTRE + np.array([side * x, y, z])


def _ear(side: float) -> np.ndarray:
    """Ear point on the head ellipsoid's side (side=1 left, -1 right), slightly back and low."""
    a, b, c = HEAD_AXES
    x, z = -0.005, -0.005
    return HEAD_CENTRE + np.array([x, side * b * np.sqrt(1 - (x / a) ** 2 - (z / c) ** 2), z])


REST = np.array([
    (0.0, 0.0, 0.96), (0.0, 0.085, 0.90), (0.0, -0.085, 0.90), (-0.01, 0.0, 1.07),      # pelv lhip rhip bell
    (0.01, 0.09, 0.50), (0.01, -0.09, 0.50), (-0.01, 0.0, 1.20), (-0.02, 0.09, 0.08),   # lkne rkne spin lank
    (-0.02, -0.09, 0.08), (-0.01, 0.0, 1.28), (0.12, 0.10, 0.02), (0.12, -0.10, 0.02),  # rank thor ltoe rtoe
    (0.0, 0.0, 1.48), (0.0, 0.075, 1.43), (0.0, -0.075, 1.43), (0.01, 0.0, 1.56),       # neck lcla rcla head
    (-0.01, 0.18, 1.43), (-0.01, -0.18, 1.43), (-0.02, 0.20, 1.15), (-0.02, -0.20, 1.15),  # lsho rsho lelb relb
    (0.0, 0.21, 0.90), (0.0, -0.21, 0.90), (0.01, 0.21, 0.82), (0.01, -0.21, 0.82),     # lwri rwri lhan rhan
    tuple(HEAD_CENTRE + np.array([0.105, 0.0, -0.03])),                                 # 24 nose
    tuple(_on_head(0.032, 0.005)),                                                       # 25 leye
    tuple(_ear(1.0)),                                                                    # 26 lear
    tuple(_on_head(-0.032, 0.005)),                                                      # 27 reye
    tuple(_ear(-1.0)),                                                                   # 28 rear
    tuple(HEAD_CENTRE + np.array([0.0, 0.0, HEAD_AXES[2]])),                            # 29 htop
])
EYES = (25, 27)

# (joint a, joint b, radius at 1.75 m, colour slot); slots: skin, hair, shirt, trousers, shoes, sleeve
LIMBS = (
    (1, 4, 0.070, "trousers"), (2, 5, 0.070, "trousers"), (4, 7, 0.052, "trousers"), (5, 8, 0.052, "trousers"),
    (7, 10, 0.040, "shoes"), (8, 11, 0.040, "shoes"), (1, 2, 0.075, "trousers"),
    (13, 16, 0.050, "shirt"), (14, 17, 0.050, "shirt"), (16, 18, 0.045, "shirt"), (17, 19, 0.045, "shirt"),
    (18, 20, 0.037, "sleeve"), (19, 21, 0.037, "sleeve"), (20, 22, 0.034, "skin"), (21, 23, 0.034, "skin"),
    (12, 15, 0.050, "skin"),
)
BALLS = ((1, 0.075, "trousers"), (2, 0.075, "trousers"), (4, 0.055, "trousers"), (5, 0.055, "trousers"),
         (7, 0.045, "shoes"), (8, 0.045, "shoes"), (16, 0.052, "shirt"), (17, 0.052, "shirt"),
         (18, 0.042, "shirt"), (19, 0.042, "shirt"), (22, 0.040, "skin"), (23, 0.040, "skin"))
SLOTS = ("skin", "hair", "shirt", "trousers", "shoes", "sleeve")


@dataclass
class Body:
    """One person's constants: size, rest skeleton, clothes."""

    height: float
    rest: np.ndarray            # (30, 3) rest joints, body frame
    offsets: np.ndarray         # (30, 3) rest[j] - rest[parent]
    head_local: np.ndarray      # (3,) head ellipsoid centre relative to joint 15 (rest)
    head_axes: np.ndarray       # (3,)
    colours: dict[str, np.ndarray]
    scale: float

    @property
    def arm(self) -> tuple[float, float, float]:
        """Upper arm, forearm and hand lengths (m)."""
        r = self.rest
        return (float(np.linalg.norm(r[18] - r[16])), float(np.linalg.norm(r[20] - r[18])),
                float(np.linalg.norm(r[22] - r[20])))


def make_body(height: float, rng: np.random.Generator) -> Body:
    """A person of `height` metres with random clothes, skin and hair colours."""
    s = height / REF_HEIGHT
    rest = REST * s
    offsets = rest - np.where(PARENTS[:, None] >= 0, rest[np.maximum(PARENTS, 0)], 0.0)
    offsets[0] = rest[0]

    def hsv(h, sat, val):
        return np.array(colorsys.hsv_to_rgb(h, sat, val), np.float32)

    skin = hsv(rng.uniform(0.02, 0.09), rng.uniform(0.25, 0.6), rng.uniform(0.3, 0.9))
    hair = hsv(rng.uniform(0.02, 0.12), rng.uniform(0.3, 0.8), rng.choice([0.04, 0.1, 0.25, 0.5]))
    shirt = hsv(rng.random(), rng.uniform(0.0, 0.9), rng.uniform(0.1, 0.95))
    colours = {"skin": skin, "hair": hair, "shirt": shirt,
               "trousers": hsv(rng.random(), rng.uniform(0.0, 0.7), rng.uniform(0.08, 0.7)),
               "shoes": hsv(rng.random(), rng.uniform(0.0, 0.5), rng.uniform(0.05, 0.6)),
               "sleeve": shirt if rng.random() < 0.6 else skin}
    return Body(height=height, rest=rest, offsets=offsets, head_local=(HEAD_CENTRE - REST[15]) * s,
                head_axes=HEAD_AXES * s, colours=colours, scale=s)


def rotvec(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (3,) of a rotation matrix."""
    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


def from_rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation matrix of an axis-angle vector (3,)."""
    return cv2.Rodrigues(np.asarray(r, np.float64).reshape(3, 1))[0]


def head_frame(direction: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """A head orientation (3, 3) whose columns are forward (= direction), left, up; no roll
    relative to world z unless `roll` (rad) is given."""
    f = np.asarray(direction, np.float64)
    f = f / np.linalg.norm(f)
    left = cross3([0.0, 0.0, 1.0], f)
    n = np.linalg.norm(left)
    left = left / n if n > 1e-6 else np.array([0.0, 1.0, 0.0])
    up = cross3(f, left)
    H = np.stack([f, left, up], axis=1)
    return H @ meshes.rot_x(roll) if roll else H


def posture_rotations(body: Body, posture: str, phase: float = 0.0, seat_height: float = 0.45,
                      lean: float = 0.0, twist: float = 0.0) -> tuple[np.ndarray, float]:
    """Local rotations (30, 3, 3) for a posture and the pelvis height above the floor (m).

    posture: "standing", "walking" (phase in rad along the gait cycle) or "sitting" (on a seat of
    `seat_height`). lean: forward torso lean (rad); twist: torso yaw relative to the pelvis (rad).
    Neck and head stay identity: `pose` sets them from the head direction.
    """
    L = np.tile(np.eye(3), (30, 1, 1))
    s = body.scale
    d = np.radians
    pelvis_z = body.rest[0, 2]
    if posture == "walking":
        sw = np.sin(phase)
        L[1], L[2] = meshes.rot_y(-d(22) * sw), meshes.rot_y(d(22) * sw)
        L[4] = meshes.rot_y(d(8) + d(40) * (0.5 + 0.5 * np.cos(phase)) ** 2)
        L[5] = meshes.rot_y(d(8) + d(40) * (0.5 - 0.5 * np.cos(phase)) ** 2)
        L[16] = meshes.rot_y(-d(18) * -sw) @ meshes.rot_x(d(6))
        L[17] = meshes.rot_y(-d(18) * sw) @ meshes.rot_x(-d(6))
        L[18] = L[19] = meshes.rot_y(-d(20))
        pelvis_z = body.rest[0, 2] - 0.02 * s * (1 - np.cos(2 * phase)) / 2
    elif posture == "sitting":
        hip_z = seat_height + 0.08 * s
        thigh = np.linalg.norm(body.rest[4] - body.rest[1])
        shin_height = body.rest[4, 2]  # knee height above the floor when the shin is vertical
        a = np.arcsin(np.clip((hip_z - shin_height) / thigh, -0.5, 0.5))
        flex = np.pi / 2 - a
        L[1] = L[2] = meshes.rot_y(-flex)
        L[4] = L[5] = meshes.rot_y(flex)
        L[16], L[17] = meshes.rot_y(-d(35)) @ meshes.rot_x(d(8)), meshes.rot_y(-d(35)) @ meshes.rot_x(-d(8))
        L[18] = L[19] = meshes.rot_y(-d(60))
        pelvis_z = hip_z + (body.rest[0, 2] - body.rest[1, 2])
        lean = lean + d(8)
    else:  # standing
        L[16], L[17] = meshes.rot_x(d(7)), meshes.rot_x(-d(7))
        L[18] = L[19] = meshes.rot_y(-d(10))
    L[3] = meshes.rot_z(twist) @ meshes.rot_y(lean)
    return L, float(pelvis_z)


def forward_kinematics(body: Body, root: np.ndarray, yaw: float, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World joints (30, 3) and global rotations (30, 3, 3) of the pelvis at `root` (3,) facing yaw."""
    G = np.empty((30, 3, 3))
    p = np.empty((30, 3))
    G[0] = meshes.rot_z(yaw) @ L[0]
    p[0] = root
    for j in range(1, 30):  # parents come before children in the huge8 order
        a = PARENTS[j]
        G[j] = G[a] @ L[j]
        p[j] = p[a] + G[a] @ body.offsets[j]
    return p, G


def set_head(body: Body, L: np.ndarray, G_thorax: np.ndarray, H: np.ndarray, max_yaw: float = np.radians(80),
             pitch=(np.radians(-60), np.radians(45))) -> np.ndarray:  # noqa: B008 - a tuple of floats: immutable
    """Write neck (12) and head (15) rotations into L (in place) so the head's global orientation
    is H (3, 3) given the thorax orientation; the turn relative to the thorax is clamped to
    anatomical limits (yaw within max_yaw, pitch within `pitch`, rad). Returns the head orientation
    actually reached."""
    R = G_thorax.T @ H  # head relative to the thorax (neck and collars add no rotation)
    f = R[:, 0]
    yaw, pit = np.arctan2(f[1], f[0]), np.arctan2(f[2], np.hypot(f[0], f[1]))
    cy, cp = np.clip(yaw, -max_yaw, max_yaw), np.clip(pit, *pitch)
    if cy != yaw or cp != pit:
        fc = np.array([np.cos(cp) * np.cos(cy), np.cos(cp) * np.sin(cy), np.sin(cp)])
        R = G_thorax.T @ head_frame(G_thorax @ fc)
    half = from_rotvec(0.5 * rotvec(R))
    L[12] = half
    L[15] = half.T @ R
    return G_thorax @ R


def reach_arm(body: Body, joints: np.ndarray, side: int, target: np.ndarray, amount: float) -> None:
    """Move one arm (side 0 = left, 1 = right) toward the world point `target`, in place.

    The hand touches the target when it is within reach, else the arm points at it. `amount` in
    [0, 1] blends from the current arm to the full reach (raising the arm over a few frames).
    Two-bone IK with the elbow pointing down and out.
    """
    sh, el, wr, ha = (16, 18, 20, 22) if side == 0 else (17, 19, 21, 23)
    a, b, c = body.arm
    S = joints[sh]
    to = target - S
    dist = np.linalg.norm(to)
    if dist < 1e-6:
        return
    u = to / dist
    w_goal = target - u * c if dist > c else S + u * 1e-3
    goal = S + (w_goal - S) * amount + (joints[wr] - S) * (1 - amount) if amount < 1 else w_goal
    dv = goal - S
    d = float(np.clip(np.linalg.norm(dv), abs(a - b) + 1e-3, a + b - 1e-4))
    u = dv / max(np.linalg.norm(dv), 1e-9)
    goal = S + u * d
    lateral = cross3([0.0, 0.0, 1.0], u)
    pole = np.array([0.0, 0.0, -1.0]) + (0.4 if side == 1 else -0.4) * lateral
    pole = pole - (pole @ u) * u
    n = np.linalg.norm(pole)
    pole = pole / n if n > 1e-6 else np.array([0.0, 0.0, -1.0])
    cos_a = (a * a + d * d - b * b) / (2 * a * d)
    alpha = np.arccos(np.clip(cos_a, -1, 1))
    E = S + a * (np.cos(alpha) * u + np.sin(alpha) * pole)
    f = (goal - E) / max(np.linalg.norm(goal - E), 1e-9)
    joints[el], joints[wr], joints[ha] = E, goal, goal + f * c


def head_ellipsoid(body: Body, joints: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Head ellipsoid centre (3,), rotation (3, 3) (columns forward, left, up) and semi-axes (3,)."""
    R = G[15]
    return joints[15] + R @ body.head_local, R, body.head_axes


def _hair_mask() -> np.ndarray:
    v, f = meshes.template("head")
    c = v[f].mean(axis=1)
    return (c[:, 2] > 0.3) | ((c[:, 0] < -0.25) & (c[:, 2] > -0.45))


_HAIR = None


def person_mesh(body: Body, joints: np.ndarray, G: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body mesh: vertices (V, 3) float32, triangles (F, 3) int32, albedo per triangle (F, 3)."""
    global _HAIR
    if _HAIR is None:
        _HAIR = _hair_mask()
    s = body.scale
    parts, cols = [], []
    col = body.colours
    lv, lf = meshes.template("limb")
    for a, b, r, slot in LIMBS:
        d = joints[b] - joints[a]
        length = np.linalg.norm(d)
        R = meshes.align_z(d)
        parts.append(((lv * np.array([r * s, r * s, length])) @ R.T + joints[a], lf))
        cols.append((len(lf), col[slot]))
    bv, bf = meshes.template("ball")
    for j, r, slot in BALLS:
        parts.append((bv * (r * s) + joints[j], bf))
        cols.append((len(bf), col[slot]))
    hv, hf = meshes.template("head")
    # torso: abdomen (pelvis to spine2) and chest (spine2 to neck), oriented by the thorax
    for a, b, w, dep, slot in ((0, 6, 0.15, 0.105, "shirt"), (6, 12, 0.175, 0.11, "shirt")):
        mid = 0.5 * (joints[a] + joints[b])
        half = 0.5 * np.linalg.norm(joints[b] - joints[a]) + 0.06 * s
        R = G[9] if a == 6 else G[3]
        z = (joints[b] - joints[a]) / max(np.linalg.norm(joints[b] - joints[a]), 1e-9)
        x = R[:, 0] - (R[:, 0] @ z) * z
        x /= np.linalg.norm(x)
        Rt = np.stack([x, cross3(z, x), z], axis=1)
        parts.append(((hv * np.array([dep * s, w * s, half])) @ Rt.T + mid, hf))
        cols.append((len(hf), col[slot]))
    c, R, ax = head_ellipsoid(body, joints, G)
    parts.append(((hv * ax) @ R.T + c, hf))
    head_cols = np.where(_HAIR[:, None], col["hair"], col["skin"])
    V, F = meshes.merge(parts)
    albedo = np.concatenate([np.repeat(c_[None], n, axis=0) for n, c_ in cols] + [head_cols]).astype(np.float32)
    return V, F, albedo
