"""Rooms: a floor, walls and ceiling, furniture (tables, shelves, cabinets, chairs) and 10-60
small objects of varied shape and size resting on surfaces in uneven clusters.

World frame: metres, z up, the floor at z = 0 spanning [0, size_x] x [0, size_y]. Every piece is
one `Instance` with its own id; ids are assigned in the order structure, furniture, objects (the
person, added per frame, takes the next id: `Room.person_id`).
"""
from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import cv2
import numpy as np

from . import meshes
from .config import SynthConfig

KINDS: tuple[str, ...] = ("object", "furniture", "structure", "person")  # codes 0..3 in the truth
SHAPE_CODES: dict[str, int] = {"box": 0, "cylinder": 1, "sphere": 2, "cone": 3, "torus": 4, "ellipsoid": 5,
                               "octahedron": 6, "table": 10, "shelf": 11, "cabinet": 12, "chair": 13,
                               "floor": 20, "wall": 21, "ceiling": 22, "person": 30}
GRID = 0.05  # free-space grid cell (m)
# The schedule of an object's placement tries: around its cluster first, widening the cluster
# every WIDEN_EVERY-th try while crowded; then every MOVE_EVERY-th try on another surface it fits
# on; from try SHRINK_AT a smaller object; after PLACE_TRIES tries it is left out.
PLACE_TRIES = 60
WIDEN_UNTIL, WIDEN_EVERY, WIDEN_FACTOR = 20, 4, 1.3
MOVE_EVERY = 5
SHRINK_AT, SHRINK_FACTOR = 45, 0.7
# Chairs (metres): seat side, thickness, leg width, back-rest height above the seat; footprint and
# clearance radii; distance of a sitter's chair from its table edge; seat heights drawn uniformly.
CHAIR_SEAT, CHAIR_SEAT_THICKNESS, CHAIR_LEG, CHAIR_BACK = 0.44, 0.04, 0.04, 0.45
CHAIR_FOOTPRINT, CHAIR_CLEARANCE, CHAIR_TABLE_OFFSET = 0.32, 0.33, 0.35
SEAT_HEIGHT = (0.42, 0.48)


@dataclass
class Instance:
    """One rigid piece of the room with its appearance."""

    id: int
    kind: str                    # one of KINDS
    shape: str                   # key of SHAPE_CODES
    vertices: np.ndarray         # (V, 3) float32 world
    triangles: np.ndarray        # (F, 3) int32
    albedo: np.ndarray           # (3,) float32 linear RGB in [0, 1]
    size: float                  # largest extent (m)
    centroid: np.ndarray         # (3,) world: mean of uniform surface samples
    samples: np.ndarray          # (S, 3) world surface samples (gaze targets are drawn from them)
    dark: bool = False
    shiny: bool = False
    tex_dir: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    tex_freq: float = 4.0        # cycles per metre of the procedural stripe texture


@dataclass
class Surface:
    """An axis-aligned horizontal rectangle objects can rest on."""

    x0: float
    x1: float
    y0: float
    y1: float
    z: float
    headroom: float              # max object height (m)

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)


@dataclass
class Seat:
    """Where a sitting person goes: chair seat centre (x, y), seat height, facing yaw (rad)."""

    xy: np.ndarray
    height: float
    yaw: float


@dataclass
class Room:
    size: np.ndarray             # (3,) x, y extent and wall height
    instances: list[Instance]
    surfaces: list[Surface]
    free: np.ndarray             # (Gy, Gx) bool: floor cells a person can stand in (clearance)
    light: np.ndarray            # (3,) unit direction the light travels (world)
    seat: Seat | None = None

    @property
    def person_id(self) -> int:
        return len(self.instances)

    def cell_xy(self, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
        """World (x, y) of free-grid cell centres."""
        return np.stack([(ix + 0.5) * GRID, (iy + 0.5) * GRID], axis=-1)


def _colour(rng: np.random.Generator, sat=(0.2, 0.9), val=(0.3, 0.95)) -> np.ndarray:
    h = rng.random()
    return np.array(colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val)), np.float32)


class _Builder:
    def __init__(self, cfg: SynthConfig, rng: np.random.Generator):
        self.cfg, self.rng = cfg, rng
        self.instances: list[Instance] = []
        self.surfaces: list[Surface] = []
        self.footprints: list[tuple[float, float, float, float]] = []  # furniture x0, x1, y0, y1

    def add(self, kind: str, shape: str, mesh: meshes.Mesh, albedo, size: float, dark=False, shiny=False) -> Instance:
        rng = self.rng
        samples = meshes.surface_samples(mesh, 64, rng).astype(np.float32)
        d = rng.normal(size=3)
        inst = Instance(id=len(self.instances), kind=kind, shape=shape, vertices=mesh[0], triangles=mesh[1],
                        albedo=np.asarray(albedo, np.float32), size=float(size),
                        centroid=samples.mean(axis=0), samples=samples, dark=dark, shiny=shiny,
                        tex_dir=d / np.linalg.norm(d), tex_freq=float(rng.uniform(2.0, 12.0)))
        self.instances.append(inst)
        return inst

    # --- shell -------------------------------------------------------------------------------
    def shell(self, sx: float, sy: float, h: float) -> None:
        rng = self.rng
        floor_col = _colour(rng, (0.1, 0.5), (0.25, 0.6))
        self.add("structure", "floor", meshes.quad([(0, 0, 0), (sx, 0, 0), (sx, sy, 0), (0, sy, 0)]), floor_col,
                 max(sx, sy))
        wall_col = _colour(rng, (0.05, 0.3), (0.6, 0.9))
        for a, b in (((0, 0), (sx, 0)), ((sx, 0), (sx, sy)), ((sx, sy), (0, sy)), ((0, sy), (0, 0))):
            q = meshes.quad([(a[0], a[1], 0), (b[0], b[1], 0), (b[0], b[1], h), (a[0], a[1], h)])
            col = np.clip(wall_col * rng.uniform(0.9, 1.1), 0, 1)
            self.add("structure", "wall", q, col, max(np.hypot(b[0] - a[0], b[1] - a[1]), h))
        if self.cfg.room.ceiling:
            q = meshes.quad([(0, 0, h), (0, sy, h), (sx, sy, h), (sx, 0, h)])
            self.add("structure", "ceiling", q, np.array([0.85, 0.85, 0.82]) * rng.uniform(0.85, 1.0), max(sx, sy))

    # --- furniture ---------------------------------------------------------------------------
    def _fits(self, x0, x1, y0, y1, sx, sy, margin=0.1, ignore=()) -> bool:
        """Whether the rectangle lies in the room and clear of every footprint but `ignore`."""
        if x0 < 0 or y0 < 0 or x1 > sx or y1 > sy:
            return False
        return all(x1 + margin <= a0 or a1 + margin <= x0 or y1 + margin <= b0 or b1 + margin <= y0
                   for a0, a1, b0, b1 in self.footprints if (a0, a1, b0, b1) not in ignore)

    @property
    def floor_size(self) -> tuple[float, float]:
        """The room's (x, y) extent as its floor mesh has it (float32 vertices)."""
        floor = self.instances[0].vertices
        return float(floor[:, 0].max()), float(floor[:, 1].max())

    def fits_beside_own_table(self, s: Surface, x: float, y: float, r: float) -> bool:
        """Whether a chair of radius r at (x, y) is clear of every footprint but its own table's
        (a chair may tuck under its table)."""
        own = [f for f in self.footprints if abs(f[0] - (s.x0 - 0.02)) < 1e-6 and abs(f[2] - (s.y0 - 0.02)) < 1e-6]
        return self._fits(x - r, x + r, y - r, y + r, *self.floor_size, margin=0.0, ignore=own)

    def _place_rect(self, w: float, d: float, sx: float, sy: float, against_wall: bool):
        """Find a footprint (x0, x1, y0, y1) and the yaw its front faces, or None."""
        rng = self.rng
        for _ in range(40):
            if against_wall:
                wall = int(rng.integers(4))
                # front faces into the room; the local width runs along the wall
                if wall in (0, 2):
                    x0 = rng.uniform(0.05, sx - w - 0.05)
                    x1 = x0 + w
                    y0, y1 = (0.02, 0.02 + d) if wall == 0 else (sy - 0.02 - d, sy - 0.02)
                    yaw = np.pi / 2 if wall == 0 else -np.pi / 2
                else:
                    y0 = rng.uniform(0.05, sy - w - 0.05)
                    y1 = y0 + w
                    x0, x1 = (sx - 0.02 - d, sx - 0.02) if wall == 1 else (0.02, 0.02 + d)
                    yaw = np.pi if wall == 1 else 0.0
            else:
                if rng.random() < 0.5:
                    w, d = d, w
                x0 = rng.uniform(0.6, max(0.61, sx - w - 0.6))
                y0 = rng.uniform(0.6, max(0.61, sy - d - 0.6))
                x1, y1 = x0 + w, y0 + d
                yaw = float(rng.integers(4)) * np.pi / 2
            if self._fits(x0, x1, y0, y1, sx, sy):
                return (x0, x1, y0, y1), yaw
        return None

    def _claim_rect(self, w: float, d: float, sx: float, sy: float, against_wall: bool):
        """`_place_rect`, and the footprint found is claimed (later furniture keeps clear of it)."""
        got = self._place_rect(w, d, sx, sy, against_wall)
        if got is not None:
            self.footprints.append(got[0])
        return got

    def table(self, sx, sy) -> None:
        rng = self.rng
        w, d, h = rng.uniform(0.8, 1.8), rng.uniform(0.6, 0.95), rng.uniform(0.70, 0.78)
        got = self._claim_rect(w, d, sx, sy, against_wall=rng.random() < 0.3)
        if got is None:
            return
        (x0, x1, y0, y1), _ = got
        t = 0.04
        parts = [meshes.box((x0, y0, h - t), (x1, y1, h))]
        for lx, ly in ((x0 + 0.03, y0 + 0.03), (x1 - 0.08, y0 + 0.03), (x0 + 0.03, y1 - 0.08), (x1 - 0.08, y1 - 0.08)):
            parts.append(meshes.box((lx, ly, 0), (lx + 0.05, ly + 0.05, h - t)))
        col = _colour(rng, (0.1, 0.6), (0.2, 0.8))
        self.add("furniture", "table", meshes.merge(parts), col, max(x1 - x0, y1 - y0))
        self.surfaces.append(Surface(x0 + 0.02, x1 - 0.02, y0 + 0.02, y1 - 0.02, h, 1.0))

    def shelf(self, sx, sy) -> None:
        rng = self.rng
        w, d, h = rng.uniform(0.8, 1.6), rng.uniform(0.3, 0.42), rng.uniform(1.3, 2.0)
        got = self._claim_rect(w, d, sx, sy, against_wall=True)
        if got is None:
            return
        (x0, x1, y0, y1), yaw = got
        n_boards = int(rng.integers(3, 6))
        t = 0.025
        zs = np.linspace(0.05, h - t, n_boards)
        parts = [meshes.box((x0, y0, z), (x1, y1, z + t)) for z in zs]
        # side panels (along the local width ends) and a back panel against the wall
        along_x = abs(np.sin(yaw)) > 0.5  # wall 0 or 2: width along x
        if along_x:
            parts += [meshes.box((x0, y0, 0), (x0 + t, y1, h)), meshes.box((x1 - t, y0, 0), (x1, y1, h))]
            parts.append(meshes.box((x0, y0, 0), (x1, y0 + t, h)) if yaw > 0
                         else meshes.box((x0, y1 - t, 0), (x1, y1, h)))
        else:
            parts += [meshes.box((x0, y0, 0), (x1, y0 + t, h)), meshes.box((x0, y1 - t, 0), (x1, y1, h))]
            parts.append(meshes.box((x1 - t, y0, 0), (x1, y1, h)) if abs(yaw) > 1
                         else meshes.box((x0, y0, 0), (x0 + t, y1, h)))
        col = _colour(rng, (0.1, 0.5), (0.2, 0.85))
        self.add("furniture", "shelf", meshes.merge(parts), col, max(w, h))
        for i, z in enumerate(zs):
            head = (zs[i + 1] - z - t - 0.02) if i + 1 < len(zs) else 0.5
            if head > 0.05:
                self.surfaces.append(Surface(x0 + 0.04, x1 - 0.04, y0 + 0.04, y1 - 0.04, float(z + t), float(head)))

    def cabinet(self, sx, sy) -> None:
        rng = self.rng
        w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.4, 0.6), rng.uniform(0.75, 1.05)
        got = self._claim_rect(w, d, sx, sy, against_wall=True)
        if got is None:
            return
        (x0, x1, y0, y1), _ = got
        col = _colour(rng, (0.0, 0.4), (0.15, 0.9))
        self.add("furniture", "cabinet", meshes.box((x0, y0, 0), (x1, y1, h)), col, max(w, h))
        self.surfaces.append(Surface(x0 + 0.03, x1 - 0.03, y0 + 0.03, y1 - 0.03, h, 1.0))

    def chair_at(self, cx: float, cy: float, yaw: float, seat_h: float, col) -> None:
        """A chair whose seat centre is (cx, cy), facing yaw (the sitter looks along yaw)."""
        s, t, leg = CHAIR_SEAT, CHAIR_SEAT_THICKNESS, CHAIR_LEG
        R = meshes.rot_z(yaw)
        local = [((-s / 2, -s / 2, seat_h - t), (s / 2, s / 2, seat_h))]
        for lx, ly in ((-s / 2, -s / 2), (s / 2 - leg, -s / 2), (-s / 2, s / 2 - leg), (s / 2 - leg, s / 2 - leg)):
            local.append(((lx, ly, 0), (lx + leg, ly + leg, seat_h - t)))
        local.append(((-s / 2 - 0.03, -s / 2, seat_h), (-s / 2, s / 2, seat_h + CHAIR_BACK)))  # back rest behind
        parts = []
        for lo, hi in local:
            v, f = meshes.box(lo, hi)
            parts.append(((v @ R.T.astype(np.float32)) + np.array([cx, cy, 0], np.float32), f))
        self.add("furniture", "chair", meshes.merge(parts), col, seat_h + CHAIR_BACK)
        r = CHAIR_FOOTPRINT
        self.footprints.append((cx - r, cx + r, cy - r, cy + r))

    # --- objects -----------------------------------------------------------------------------
    def objects(self, sx: float, sy: float, occupied: np.ndarray, focus: Surface | None = None) -> None:
        cfg, rng = self.cfg.objects, self.rng
        n = int(rng.integers(cfg.count[0], cfg.count[1] + 1))
        if n == 0:
            return
        floor = Surface(0.3, sx - 0.3, 0.3, sy - 0.3, 0.0, 1.0)
        surfs = self.surfaces
        k = max(1, int(np.ceil(n * (1.0 - cfg.clustering)))) if cfg.clustering < 1 else 1
        # cluster centres: on furniture surfaces by area, some on the floor
        centres: list[tuple[Surface, np.ndarray, float]] = []
        for _ in range(k):
            if not surfs or rng.random() < cfg.floor_fraction:
                s = floor
            else:
                a = np.array([x.area for x in surfs])
                s = surfs[int(rng.choice(len(surfs), p=a / a.sum()))]
            if focus is not None and not centres:  # the table a sitting person works at
                s = focus
            c = np.array([rng.uniform(s.x0, s.x1), rng.uniform(s.y0, s.y1)])
            centres.append((s, c, rng.uniform(*cfg.cluster_spread)))
        weights = rng.dirichlet(np.ones(k)) if k > 1 else np.ones(1)
        placed: list[tuple[Surface, np.ndarray, float]] = []
        lo, hi = np.log(cfg.size[0]), np.log(cfg.size[1])
        for _ in range(n):
            ci = int(rng.choice(k, p=weights))
            s, c, spread = centres[ci]
            shape = str(rng.choice(list(cfg.shapes)))
            L = float(np.exp(rng.uniform(lo, hi)))
            for attempt in range(PLACE_TRIES):
                if attempt < WIDEN_UNTIL and attempt % WIDEN_EVERY == WIDEN_EVERY - 1:  # crowded: widen the cluster
                    spread *= WIDEN_FACTOR
                if attempt >= WIDEN_UNTIL and attempt % MOVE_EVERY == 0:  # the cluster is full: another surface
                    s = self._fitting_surface(surfs + [floor], shape, L) or s
                    c, spread = np.array([0.5 * (s.x0 + s.x1), 0.5 * (s.y0 + s.y1)]), 10.0
                if attempt == SHRINK_AT:  # nowhere: a smaller one
                    L = max(cfg.size[0], SHRINK_FACTOR * L)
                spot = self._try_spot(s, c, spread, shape, L, placed, occupied, floor)
                if spot is not None:
                    p, r, dims = spot
                    break
            else:
                continue
            placed.append((s, p, r))
            R = meshes.rot_z(rng.uniform(0, 2 * np.pi))
            v, f = meshes.transformed(shape, dims, R, (p[0], p[1], 0.0))
            v[:, 2] += np.float32(s.z) - v[:, 2].min()  # rest on the surface (tessellated bottoms too)
            mesh = (v, f)
            dark = rng.random() < cfg.dark_fraction
            shiny = rng.random() < cfg.shiny_fraction
            col = _colour(rng, (0.0, 0.1), (0.01, 0.05)) if dark else _colour(rng)
            self.add("object", shape, mesh, col, float(max(dims)), dark=dark, shiny=shiny)


    def _fitting_surface(self, surfs: list[Surface], shape: str, L: float) -> Surface | None:
        """A surface wide enough for an object of largest extent L (chosen by area), or None."""
        r_min = 0.5 * L * (0.5 if shape in ("box", "ellipsoid", "cylinder", "cone") else 1.0)
        fit = [x for x in surfs if min(x.x1 - x.x0, x.y1 - x.y0) >= 2 * r_min]
        if not fit:
            return None
        a = np.array([x.area for x in fit])
        return fit[int(self.rng.choice(len(fit), p=a / a.sum()))]

    def _try_spot(self, s: Surface, c: np.ndarray, spread: float, shape: str, L: float,
                  placed: list[tuple[Surface, np.ndarray, float]], occupied: np.ndarray,
                  floor: Surface) -> tuple[np.ndarray, float, np.ndarray] | None:
        """One placement try on surface s around c: (position (2,), footprint radius, dims (3,)), or
        None when the object does not fit, overlaps a placed one, or stands on occupied floor."""
        dims = _object_dims(shape, L, self.rng)
        if dims[2] > s.headroom:
            dims = dims * (s.headroom / dims[2])
        r = 0.5 * float(np.hypot(dims[0], dims[1]))
        if 2 * r > min(s.x1 - s.x0, s.y1 - s.y0):
            return None
        p = c + self.rng.normal(0, spread, 2)
        p = np.clip(p, [s.x0 + r, s.y0 + r], [s.x1 - r, s.y1 - r])
        if any(o is s and np.hypot(*(p - q)) < r + rr + 0.01 for o, q, rr in placed):
            return None
        if s is floor and _hits_grid(occupied, p, r + 0.05):
            return None
        return p, r, dims

def _object_dims(shape: str, L: float, rng: np.random.Generator) -> np.ndarray:
    """Template scale (x, y, z) for an object whose largest extent is L."""
    if shape == "box":
        d = np.array([L, L * rng.uniform(0.3, 1.0), L * rng.uniform(0.2, 1.0)])
        return rng.permutation(d) if rng.random() < 0.5 else d
    if shape in ("cylinder", "cone"):
        if rng.random() < 0.5:
            return np.array([L, L, L * rng.uniform(0.3, 1.0)])
        dd = L * rng.uniform(0.25, 1.0)
        return np.array([dd, dd, L])
    if shape == "sphere":
        return np.array([L, L, L])
    if shape == "torus":
        return np.array([L, L, L])  # the template is flat: height L/4
    if shape == "ellipsoid":
        return L * np.array([1.0, rng.uniform(0.4, 1.0), rng.uniform(0.4, 1.0)])
    return np.array([L, L, L])  # octahedron


def _hits_grid(occupied: np.ndarray, p: np.ndarray, r: float) -> bool:
    ix0, ix1 = int((p[0] - r) / GRID), int((p[0] + r) / GRID) + 1
    iy0, iy1 = int((p[1] - r) / GRID), int((p[1] + r) / GRID) + 1
    return bool(occupied[max(iy0, 0):iy1, max(ix0, 0):ix1].any())


def _occupancy(sx: float, sy: float, footprints) -> np.ndarray:
    occ = np.zeros((int(np.ceil(sy / GRID)), int(np.ceil(sx / GRID))), bool)
    for x0, x1, y0, y1 in footprints:
        occ[int(y0 / GRID):int(np.ceil(y1 / GRID)), int(x0 / GRID):int(np.ceil(x1 / GRID))] = True
    return occ


def build_room(cfg: SynthConfig, rng: np.random.Generator, sitting: bool = False) -> Room:
    """Sample a furnished room with objects. With `sitting`, a chair at a table side is added and
    returned as `Room.seat` (the chair faces the table)."""
    rc = cfg.room
    sx, sy, h = rng.uniform(*rc.size_x), rng.uniform(*rc.size_y), rng.uniform(*rc.height)
    b = _Builder(cfg, rng)
    b.shell(sx, sy, h)
    n_tables = int(rng.integers(rc.tables[0], rc.tables[1] + 1))
    if sitting:
        n_tables = max(n_tables, 1)
    for _ in range(n_tables):
        b.table(sx, sy)
    for _ in range(int(rng.integers(rc.shelves[0], rc.shelves[1] + 1))):
        b.shelf(sx, sy)
    for _ in range(int(rng.integers(rc.cabinets[0], rc.cabinets[1] + 1))):
        b.cabinet(sx, sy)
    chair_col = _colour(rng, (0.1, 0.6), (0.2, 0.8))
    seat, focus = None, None
    if sitting:
        tables = [(s, i) for i, s in enumerate(b.surfaces) if s.headroom >= 1.0 and 0.6 < s.z < 0.8]
        for s, _ in tables:
            cx, cy = 0.5 * (s.x0 + s.x1), 0.5 * (s.y0 + s.y1)
            # try the four sides, long sides first
            d = CHAIR_TABLE_OFFSET
            sides = [(cx, s.y0 - d, np.pi / 2), (cx, s.y1 + d, -np.pi / 2), (s.x0 - d, cy, 0.0), (s.x1 + d, cy, np.pi)]
            for sx_, sy_, yaw in sides:
                x, y = sx_ + rng.uniform(-0.15, 0.15) * (yaw in (np.pi / 2, -np.pi / 2)), sy_
                r = CHAIR_CLEARANCE
                if b._fits(x - r, x + r, y - r, y + r, sx, sy, margin=0.0) or b.fits_beside_own_table(s, x, y, r):
                    seat_h = float(rng.uniform(*SEAT_HEIGHT))
                    b.chair_at(x, y, yaw, seat_h, chair_col)
                    seat = Seat(np.array([x, y]), seat_h, float(yaw))
                    focus = s
                    break
            if seat is not None:
                break
    for _ in range(int(rng.integers(rc.chairs[0], rc.chairs[1] + 1))):
        got = b._place_rect(0.5, 0.5, sx, sy, against_wall=False)
        if got is not None:
            (x0, x1, y0, y1), yaw = got
            b.chair_at(0.5 * (x0 + x1), 0.5 * (y0 + y1), yaw, float(rng.uniform(*SEAT_HEIGHT)), chair_col)
    occ = _occupancy(sx, sy, b.footprints)
    b.objects(sx, sy, occ, focus)
    # the person's free space: off furniture and floor objects, 0.3 m from walls and furniture
    for inst in b.instances:
        if inst.kind == "object" and inst.vertices[:, 2].min() < 0.01:
            lo, hi = inst.vertices[:, :2].min(0), inst.vertices[:, :2].max(0)
            b.footprints.append((lo[0], hi[0], lo[1], hi[1]))
    occ = _occupancy(sx, sy, b.footprints)
    occ[0, :] = occ[-1, :] = True
    occ[:, 0] = occ[:, -1] = True
    dist = cv2.distanceTransform((~occ).astype(np.uint8), cv2.DIST_L2, 5) * GRID
    free = dist >= 0.3
    a = rng.uniform(0, 2 * np.pi)
    light = np.array([0.5 * np.cos(a), 0.5 * np.sin(a), -1.0])
    return Room(size=np.array([sx, sy, h]), instances=b.instances, surfaces=b.surfaces, free=free,
                light=light / np.linalg.norm(light), seat=seat)
