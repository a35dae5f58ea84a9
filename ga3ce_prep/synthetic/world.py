"""Scene and frame sampling: a room, a person, one or more cameras, and a continuous timeline of
fixations (gaze targets with dwell times) along which the person stands, sits or walks.

`Scene(fmt, cfg, K, width, height, rng)` builds everything from one generator; given a pre-built
`room` (one room recorded in several sessions), it draws only the person, cameras and timeline
from `rng`. `Scene.steps(n)` yields one `Step` per time step with the person's world-frame state
and each camera's rendered `View`. Conversion to camera-frame truth is
`Scene.truth(step, camera_index)`.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..geometry import project, scale_intrinsics
from . import gaze as gz
from .camera import Camera, ellipsoid_bbox, sample_camera
from .config import POSTURES, SynthConfig
from .noise import NoiseBank
from .person import (
    EYES,
    Body,
    forward_kinematics,
    head_ellipsoid,
    head_frame,
    make_body,
    person_mesh,
    posture_rotations,
    reach_arm,
    set_head,
)
from .render import PersonScene, StaticScene, View, render_person, render_static
from .room import GRID, KINDS, SHAPE_CODES, Room, build_room
from .targets import OBJECT, SPACE, Target, TargetSampler
from .truth import ObjectTable, TruthFrame


class SceneError(ConfigError):
    """No valid layout was found for a scene (the config leaves no room for person and camera)."""


@dataclass
class Fixation:
    start: int
    end: int
    target: Target
    head_follow: float
    body_follow: float
    jitter: np.ndarray           # (3,) head error rotation vector (rad)
    reach_side: int              # -1 none, 0 left, 1 right
    eye_cap: float               # this fixation's eye-in-head offset cap (rad)


@dataclass
class Step:
    """The person at one time step (world frame) and what each camera sees."""

    t: int
    joints: np.ndarray           # (30, 3)
    G: np.ndarray                # (30, 3, 3) global joint rotations
    eye: np.ndarray              # (3,) eye midpoint
    target: Target
    gaze: np.ndarray             # (3,) unit, eye -> target
    head_dir: np.ndarray         # (3,) unit
    head_centre: np.ndarray      # (3,) head ellipsoid centre
    head_R: np.ndarray           # (3, 3) head ellipsoid axes (columns)
    head_axes: np.ndarray        # (3,) semi-axes
    posture: int                 # index into config.POSTURES
    reaching: bool
    mesh: tuple[np.ndarray, np.ndarray, np.ndarray]  # person vertices, triangles, albedo
    views: list[View]


PLACE_ATTEMPTS = 8  # rooms sampled (or, in a given room, person placements tried) before SceneError


class Scene:
    """One scene: room, person, cameras, static renders and the gaze timeline. Without `room` the
    room is sampled from `rng` too (resampled until a placement works); with it (built with a seat,
    `build_room(..., sitting=True)`, so a session may sit) only the person's placement is retried."""

    def __init__(self, fmt: str, cfg: SynthConfig, K: np.ndarray, width: int, height: int,
                 rng: np.random.Generator, room: Room | None = None):
        self.fmt, self.cfg, self.rng = fmt, cfg, rng
        self.width, self.height, self.K = width, height, K
        pc = cfg.person
        names = list(pc.postures)
        w = np.array([pc.postures[n] for n in names], float)
        self.posture = names[int(rng.choice(len(names), p=w / w.sum()))]
        self.body: Body = make_body(float(rng.uniform(*pc.height)), rng)
        given = room
        for _attempt in range(PLACE_ATTEMPTS):
            room = given if given is not None else build_room(cfg, rng, sitting=self.posture == "sitting")
            if self.posture == "sitting" and room.seat is None:
                self.posture = "standing"
            if self._place(room):
                break
        else:
            where = "the given room" if given is not None else f"{PLACE_ATTEMPTS} sampled rooms"
            raise SceneError(f"no camera could see the person in {where} ({PLACE_ATTEMPTS} placements); widen "
                             "camera.distance or camera.height, or room.size_x / room.size_y")
        self.room: Room = room
        self.views = [render_static(self.static, cam, cfg.render) for cam in self.cameras]
        self.banks = [NoiseBank(rng, height, width) for _ in self.cameras]
        self.sampler = TargetSampler(room, self.static, self.cameras, self.views, cfg.gaze, in_front=fmt != "gafa")
        self.walkable = self._walkable() if self.posture == "walking" else None
        if self.walkable is not None and self.walkable.sum() < 20:
            self.posture, self.walkable = "standing", None

    # --- layout ------------------------------------------------------------------------------
    def _head_point(self, xy: np.ndarray) -> np.ndarray:
        s = self.body.scale
        if self.posture == "sitting":
            assert self.room.seat is not None  # a room without a seat makes the person stand (__init__)
            z = self.room.seat.height + 0.78 * s
        else:
            z = 1.62 * s
        return np.array([xy[0], xy[1], z])

    def _place(self, room: Room) -> bool:
        """Choose the person's home (position, heading) and cameras that see it."""
        rng, cfg = self.rng, self.cfg
        self.room = room
        self.static = StaticScene(room)
        found = None
        for _ in range(6):
            if self.posture == "sitting":
                seat = room.seat
                assert seat is not None  # a room without a seat makes the person stand (__init__)
                home, heading = seat.xy - 0.08 * np.array([np.cos(seat.yaw), np.sin(seat.yaw)]), seat.yaw
            else:
                iy, ix = np.nonzero(room.free)
                if not len(iy):
                    return False
                k = int(rng.integers(len(iy)))
                home = room.cell_xy(iy[k], ix[k]) + rng.uniform(-GRID / 2, GRID / 2, 2)
                if room.surfaces and rng.random() < 0.6:
                    s = room.surfaces[int(rng.integers(len(room.surfaces)))]
                    toward = np.array([0.5 * (s.x0 + s.x1), 0.5 * (s.y0 + s.y1)]) - home
                    heading = float(np.arctan2(toward[1], toward[0]))
                else:
                    heading = float(rng.uniform(-np.pi, np.pi))
            head = self._head_point(home)
            must = np.stack([head, np.array([home[0], home[1], head[2] * 0.6])])
            n = int(rng.integers(cfg.camera.count[0], cfg.camera.count[1] + 1))
            az0 = heading + rng.uniform(-1.2, 1.2)  # cameras tend to see the face side
            cams = []
            for c in range(n):
                # of a few valid mounts, keep the one that sees the most objects (as a camera set up
                # to record someone handling things would)
                best, best_score = None, -1
                for _ in range(3):
                    cam = sample_camera(rng, cfg.camera, self.K, self.width, self.height, room.size, home,
                                        0.75 * head[2], must[:1], lambda C, P: bool(self.static.clear_path(C, P).all()),
                                        azimuth=az0 + 2 * np.pi * c / n)
                    if cam is None:
                        break
                    score = self._objects_seen(cam, head, heading)
                    if score > best_score:
                        best, best_score = cam, score
                if best is None:
                    break
                cams.append(best)
                if c == 0:
                    primary_score = best_score
            # keep the layout whose primary camera sees the most usable objects; stop at 3
            if len(cams) == n and (found is None or primary_score > found[0]):
                found = (primary_score, home, heading, cams)
                if primary_score >= 3:
                    break
        if found is None:
            return False
        _, self.home, self.heading0, self.cameras = found
        return True

    def _objects_seen(self, cam: Camera, head: np.ndarray, heading: float) -> int:
        """How many objects a camera sees (at least ~30 px at 640x480, from a quarter-size render)
        that the person at `head` facing `heading` could look at (gaze.max_target_yaw,
        gaze.object_distance)."""
        small = Camera(K=scale_intrinsics(cam.K, 0.25, 0.25), width=max(8, cam.width // 4),
                       height=max(6, cam.height // 4), R=cam.R, C=cam.C)
        inst = self.static.cast(small.rays().reshape(-1, 6))["instance"]
        n = len(self.room.instances)
        px = np.bincount(inst[inst >= 0].astype(np.int64), minlength=n)[:n]
        g = self.cfg.gaze
        d = np.stack([i.centroid for i in self.room.instances]) - head
        dist = np.linalg.norm(d, axis=1)
        yaw = np.abs((np.arctan2(d[:, 1], d[:, 0]) - heading + np.pi) % (2 * np.pi) - np.pi)
        usable = np.array([i.kind == "object" for i in self.room.instances]) \
            & (yaw <= np.radians(g.max_target_yaw)) & (dist >= g.object_distance[0]) & (dist <= g.object_distance[1])
        return int(np.count_nonzero(usable & (px * 16 * (640 * 480) / (cam.width * cam.height) >= 30)))

    def _walkable(self) -> np.ndarray:
        """Free floor cells where a walking person's head and feet stay in the primary view."""
        room, cam, s = self.room, self.cameras[0], self.body.scale
        iy, ix = np.nonzero(room.free)
        xy = room.cell_xy(iy, ix)
        head = np.column_stack([xy, np.full(len(xy), 1.62 * s)])
        feet = np.column_stack([xy, np.full(len(xy), 0.1)])
        m = 0.04 * min(self.width, self.height)
        ok = cam.in_image(head, m) & cam.in_image(feet, 0.0)
        for c in self.cameras[:1]:
            ok &= np.linalg.norm(xy - c.C[:2], axis=1) > 1.2
        out = np.zeros_like(room.free)
        out[iy[ok], ix[ok]] = True
        return out

    # --- timeline ----------------------------------------------------------------------------
    def _new_fixation(self, t: int, eye: np.ndarray, heading: float, turn: bool) -> Fixation:
        rng, g = self.rng, self.cfg.gaze
        target = self.sampler.sample(rng, eye, heading, turn)
        dwell = max(1, int(round(rng.uniform(*g.dwell) / self.cfg.person.frame_dt)))
        reach = -1
        if target.kind == OBJECT and rng.random() < g.reach_prob:
            d = target.point - eye
            side = gz.wrap(np.arctan2(d[1], d[0]) - heading)
            reach = 0 if side > 0 else 1  # the arm on the target's side (y is left)
        jitter = np.radians(g.head_jitter) * rng.normal(size=3)
        cap = np.radians(g.eye_offset_max) * float(rng.uniform(1.0 - g.eye_offset_cap_spread, 1.0))
        return Fixation(t, t + dwell, target, float(rng.uniform(*g.head_follow)), float(rng.uniform(*g.body_follow)),
                        jitter, reach, cap)

    def steps(self, n: int) -> Iterator[Step]:
        """The person's n time steps, rendered by every camera."""
        rng, cfg, body = self.rng, self.cfg, self.body
        dt, g = cfg.person.frame_dt, cfg.gaze
        s = body.scale
        pos, heading = self.home.copy(), self.heading0
        phase = float(rng.uniform(0, 2 * np.pi))
        speed = float(rng.uniform(*cfg.person.walk_speed))
        stride = 1.3 * s
        waypoint = None
        fix: Fixation | None = None
        prev_head = None
        prev_yaw = None
        a_head = 1.0 - np.exp(-dt / g.head_smoothing) if g.head_smoothing > 0 else 1.0
        a_body = 1.0 - np.exp(-dt / (2 * g.head_smoothing)) if g.head_smoothing > 0 else 1.0
        sway = rng.uniform(0, 2 * np.pi, 2)
        posture = self.posture
        seat_h = self.room.seat.height if self.room.seat is not None else 0.45
        for t in range(n):
            # motion
            if posture == "walking":
                pos, heading, waypoint, moved = self._walk(pos, heading, waypoint, speed * dt)
                phase += 2 * np.pi * moved / stride
            root_xy = pos.copy()
            if posture == "standing":
                root_xy = pos + cfg.person.sway * np.sin(0.7 * t * dt + sway)
            eye_est = np.array([root_xy[0], root_xy[1], self._head_point(root_xy)[2] - 0.03 * s]) \
                + 0.08 * s * np.array([np.cos(heading), np.sin(heading), 0.0])
            # fixation: a new one when it is over or the target fell behind or too close; again
            # when the head cannot turn far enough to keep the eye-in-head offset under its cap
            if fix is not None:
                d = fix.target.point - eye_est
                if (t >= fix.end or np.linalg.norm(d) < 0.35
                        or abs(gz.wrap(np.arctan2(d[1], d[0]) - heading)) > np.radians(g.max_target_yaw)):
                    fix = None
            for attempt in range(4):
                if fix is None:
                    fix = self._new_fixation(t, eye_est, heading, turn=posture == "standing")
                    d = fix.target.point - eye_est
                    off = gz.wrap(np.arctan2(d[1], d[0]) - heading)
                    if posture == "standing" and abs(off) > np.radians(60):  # turn round to it
                        heading = gz.wrap(heading + off - np.sign(off) * np.radians(rng.uniform(0, 40)))
                cap = fix.eye_cap + np.radians(0.5)
                sol = self._solve(fix, root_xy, eye_est, heading, posture, phase, seat_h, prev_yaw, prev_head,
                                  a_head, a_body)
                if gz.angle(sol[3], sol[4]) > cap and prev_yaw is not None:
                    # the smoothed body and head lag behind a large turn: turn at once instead
                    sol = self._solve(fix, root_xy, eye_est, heading, posture, phase, seat_h, None, None,
                                      a_head, a_body)
                joints, G, eye, gaze, head_dir, yaw_state = sol
                if gz.angle(gaze, head_dir) <= cap or attempt == 3:
                    break
                fix = None
            assert fix is not None  # the attempts end with one (the last is kept)
            target = fix.target.point
            prev_head, prev_yaw = head_dir, yaw_state
            reaching = fix.reach_side >= 0
            if reaching:
                amount = min(1.0, (t - fix.start + 1) * dt / max(g.reach_ramp, 1e-6))
                reach_arm(body, joints, fix.reach_side, target, amount)
            hc, hR, hax = head_ellipsoid(body, joints, G)
            mesh = person_mesh(body, joints, G)
            person = PersonScene(*mesh)
            views = [render_person(v, cam, person, self.room.person_id, self.room.light, cfg.render)
                     for v, cam in zip(self.views, self.cameras)]
            yield Step(t, joints, G, eye, fix.target, gaze, head_dir, hc, hR, hax, POSTURES.index(posture),
                       reaching, mesh, views)

    def _solve(self, fix: Fixation, root_xy, eye_est, heading, posture, phase, seat_h, prev_yaw, prev_head,
               a_head, a_body):
        """Pose the person for one fixation: the torso follows the gaze's yaw, the head follows
        its direction, the eyes do the rest. Returns joints, rotations, eye, gaze, head direction
        and the smoothed torso yaw (standing) or twist (walking, sitting)."""
        body, g = self.body, self.cfg.gaze
        target = fix.target.point
        g_est = gz.unit(target - eye_est)
        dyaw = fix.body_follow * gz.wrap(gz.yaw_of(g_est) - heading)
        if posture == "standing":
            yaw, twist = heading + dyaw, 0.0
            if prev_yaw is not None:
                yaw = prev_yaw + a_body * gz.wrap(yaw - prev_yaw)
            state = yaw
        else:
            lim = np.radians(g.max_torso_twist)
            twist = float(np.clip(dyaw, -lim, lim))
            if prev_yaw is not None:
                twist = prev_yaw + a_body * (twist - prev_yaw)
            state, yaw = twist, heading
        pitch = np.arcsin(np.clip(g_est[2], -1, 1))
        lean = float(np.clip(-0.25 * pitch, 0.0, np.radians(15))) if posture != "walking" else np.radians(3)
        L, pelvis_z = posture_rotations(body, posture, phase, seat_h, lean, twist)
        root = np.array([root_xy[0], root_xy[1], pelvis_z])
        joints, G = forward_kinematics(body, root, yaw, L)
        torso_fwd = G[9][:, 0]
        for _ in range(3):  # the eye moves with the head: iterate to a fixed point
            eye = joints[list(EYES)].mean(axis=0)
            gaze = gz.unit(target - eye)
            h = gz.head_direction(gaze, torso_fwd, fix.head_follow, fix.eye_cap, fix.jitter,
                                  prev_head, a_head if prev_head is not None else 1.0)
            set_head(body, L, G[9], head_frame(h))
            joints, G = forward_kinematics(body, root, yaw, L)
        eye = joints[list(EYES)].mean(axis=0)
        return joints, G, eye, gz.unit(target - eye), G[15][:, 0].copy(), state

    def truth(self, step: Step, c: int, frame_id: str, split: str, scene: str, camera: str, room: int = 0,
              session: int = 0) -> TruthFrame:
        """Camera c's exact truth for one step (camera frame), keyed by the dataset's frame id;
        `room` and `session` index the recording (generation.generate)."""
        cam, view, K = self.cameras[c], step.views[c], self.K
        W, H = self.width, self.height
        to = cam.to_cam
        eye, tgt, hc = to(step.eye), to(step.target.point), to(step.head_centre)
        head_R = cam.R @ step.head_R
        clip = np.array([0, 0, W - 1, H - 1], float)
        if hc[2] - step.head_axes.max() > 0.05:  # the whole head in front of the camera
            hb = np.clip(ellipsoid_bbox(K, hc, head_R, step.head_axes), clip[:2].tolist() * 2, clip[2:].tolist() * 2)
        else:
            hb = np.full(4, np.nan)
        uv = project(to(step.mesh[0]), K)
        uv = uv[np.isfinite(uv).all(axis=1)]
        bb = np.concatenate([uv.min(0), uv.max(0)]) if len(uv) else np.full(4, np.nan)
        bb = np.clip(bb, clip[:2].tolist() * 2, clip[2:].tolist() * 2)
        gaze_2d = project(tgt, K)
        visible = False
        if step.target.kind in (OBJECT, SPACE) and np.isfinite(gaze_2d).all():
            u, v = (int(round(x)) for x in gaze_2d)
            if 0 <= u < W and 0 <= v < H:
                z = float(view.depth[v, u])
                if step.target.kind == OBJECT:
                    visible = bool(view.instance[v, u] == step.target.instance
                                   and abs(z - tgt[2]) < 0.01 + 0.01 * tgt[2])
                else:
                    visible = z == 0 or z > tgt[2]
        insts = self.room.instances
        n = len(insts) + 1
        pix = np.bincount(view.instance[view.instance >= 0].astype(np.int64), minlength=n)[:n]
        cen = np.concatenate([np.stack([i.centroid for i in insts]), step.mesh[0].mean(axis=0, keepdims=True)])
        objects = ObjectTable(
            instance=np.arange(n, dtype=np.int32),
            kind=np.array([KINDS.index(i.kind) for i in insts] + [KINDS.index("person")], np.int8),
            shape=np.array([SHAPE_CODES[i.shape] for i in insts] + [SHAPE_CODES["person"]], np.int8),
            centroid=to(cen), pixels=pix.astype(np.int32),
            size=np.array([i.size for i in insts] + [self.body.height], np.float32))
        return TruthFrame(
            frame_id=frame_id, split=split, scene=scene, camera=camera, K=K.copy(), image_size=np.array([W, H]),
            pose=to(step.joints), eye=eye, gaze_target=tgt, gaze=cam.dir_to_cam(step.gaze),
            head_dir=cam.dir_to_cam(step.head_dir), head_center=hc, chest_pos=to(step.joints[9]),
            chest_dir=cam.dir_to_cam(step.G[9][:, 0]), head_R=head_R, head_axes=step.head_axes.copy(),
            target_kind=step.target.kind, target_instance=step.target.instance, target_visible=visible,
            head_box=hb, body_box=bb, eye_2d=project(eye, K), gaze_2d=gaze_2d, R_w2c=cam.R.copy(),
            cam_center=cam.C.copy(), posture=step.posture, person_height=self.body.height, reaching=step.reaching,
            time_index=step.t, room=room, session=session, objects=objects, depth=view.depth,
            instance=view.instance)

    def _walk(self, pos, heading, waypoint, step):
        """Advance a walking person by `step` metres toward its waypoint, turning smoothly."""
        rng, room = self.rng, self.room
        free = self.walkable
        iy, ix = np.nonzero(free)
        for _ in range(4):
            if waypoint is None or np.linalg.norm(waypoint - pos) < 0.3:
                k = int(rng.integers(len(iy)))
                waypoint = room.cell_xy(iy[k], ix[k])
            d = waypoint - pos
            want = float(np.arctan2(d[1], d[0]))
            turn = gz.wrap(want - heading)
            max_turn = 2.5 * self.cfg.person.frame_dt
            new_heading = heading + float(np.clip(turn, -max_turn, max_turn))
            nxt = pos + step * np.array([np.cos(new_heading), np.sin(new_heading)])
            if self._walkable_at(nxt):
                return nxt, new_heading, waypoint, step
            nxt = pos + step * np.array([np.cos(want), np.sin(want)])
            if abs(turn) < np.pi / 2 and self._walkable_at(nxt):
                return nxt, heading + 0.5 * turn, waypoint, step
            waypoint = None
        return pos, heading, None, 0.0  # boxed in: stand for a step

    def _walkable_at(self, xy: np.ndarray) -> bool:
        ix, iy = int(xy[0] / GRID), int(xy[1] / GRID)
        f = self.walkable
        assert f is not None  # a walking person's
        return 0 <= iy < f.shape[0] and 0 <= ix < f.shape[1] and bool(f[iy, ix])

