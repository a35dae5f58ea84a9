"""The synthetic world's knobs: one dataclass per concept, gathered in `SynthConfig`.

Every field is documented in docs/synthetic.md. Ranges are `(low, high)` tuples sampled uniformly
unless said otherwise; lengths in metres, angles in degrees (knobs are read by people), times in
seconds. `SynthConfig.for_format(fmt)` gives the defaults of one dataset format (GFIE, CAD-120 and
GAFA differ in target mix, postures, frame rate and camera count); `load_config(fmt, yaml_path)`
applies a YAML override file on top, section by section. A named preset (`presets/<name>.yaml`
in this package: `load_preset`) fixes a format, a seed offset and config sections, applied
between the format's defaults and the YAML file.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError
from ..params import load_yaml

FORMATS: tuple[str, ...] = ("gfie", "cad120", "gafa")
TARGET_KINDS: tuple[str, ...] = ("object", "space", "out_of_view")
POSTURES: tuple[str, ...] = ("standing", "sitting", "walking")
SHAPES: tuple[str, ...] = ("box", "cylinder", "sphere", "cone", "torus", "ellipsoid", "octahedron")


@dataclass
class RoomConfig:
    """Room shell and furniture counts."""

    size_x: tuple[float, float] = (4.5, 8.0)     # floor extent along world x (m)
    size_y: tuple[float, float] = (4.5, 8.0)     # floor extent along world y (m)
    height: tuple[float, float] = (2.6, 3.2)     # wall height (m)
    ceiling: bool = True
    tables: tuple[int, int] = (1, 3)
    shelves: tuple[int, int] = (1, 3)
    cabinets: tuple[int, int] = (0, 2)
    chairs: tuple[int, int] = (0, 3)             # extra chairs (a sitting person always gets one)


@dataclass
class ObjectConfig:
    """Small objects on surfaces (tables, shelf boards, cabinet tops, floor)."""

    count: tuple[int, int] = (10, 60)            # objects per room
    size: tuple[float, float] = (0.04, 0.5)      # largest extent (m), log-uniform
    shapes: tuple[str, ...] = SHAPES
    clustering: float = 0.7                      # 0 = spread uniformly over surfaces, 1 = one cluster
    cluster_spread: tuple[float, float] = (0.06, 0.25)  # std of objects around a cluster centre (m)
    floor_fraction: float = 0.1                  # share of cluster centres on the floor
    dark_fraction: float = 0.1                   # objects with near-black albedo (depth holes)
    shiny_fraction: float = 0.1                  # objects with specular surfaces (depth holes)


@dataclass
class PersonConfig:
    """The person: body size, posture mix, motion."""

    height: tuple[float, float] = (1.5, 1.95)
    postures: dict[str, float] = field(default_factory=lambda: {"standing": 0.5, "sitting": 0.2, "walking": 0.3})
    walk_speed: tuple[float, float] = (0.7, 1.3)  # m/s
    frame_dt: float = 0.2                        # seconds between frames
    sway: float = 0.02                           # standing sway amplitude (m)


@dataclass
class GazeConfig:
    """Where the person looks and how head, body and arm follow."""

    target_mix: dict[str, float] = field(default_factory=lambda: {"object": 0.85, "space": 0.10, "out_of_view": 0.05})
    dwell: tuple[float, float] = (0.4, 2.5)      # seconds per fixation
    object_distance: tuple[float, float] = (0.4, 4.5)  # eye-to-target distance of object targets (m)
    max_target_yaw: float = 110.0                # targets within this yaw of the person's heading (deg)
    head_follow: tuple[float, float] = (0.15, 0.5)  # share of the torso-to-gaze angle the head turns
    eye_offset_max: float = 25.0                 # eye-in-head offset cap (deg): the head catches up beyond it
    eye_offset_cap_spread: float = 0.4           # per fixation the cap is eye_offset_max * U(1 - spread, 1)
    head_jitter: float = 3.0                     # random head direction error, std per axis (deg)
    body_follow: tuple[float, float] = (0.1, 0.5)  # share of the heading-to-gaze yaw the torso turns
    max_torso_twist: float = 45.0                # walking: torso yaw relative to the pelvis (deg)
    head_smoothing: float = 0.15                 # head direction time constant (s); 0 = none
    reach_prob: float = 0.15                     # object fixations with an arm reaching/pointing
    reach_ramp: float = 0.3                      # seconds to raise the arm


@dataclass
class CameraConfig:
    """Camera mounts (surveillance / Kinect-like) and intrinsics."""

    height: tuple[float, float] = (1.0, 3.0)     # optical centre above the floor (m)
    distance: tuple[float, float] = (1.5, 6.0)   # to the person (m)
    yaw_offset: float = 15.0                     # aim off the person by up to this yaw (deg)
    pitch_offset: float = 8.0                    # and this pitch (deg)
    roll: float = 0.0                            # max |roll| (deg); 0 keeps the x axis horizontal
    count: tuple[int, int] = (1, 1)              # cameras per scene viewing the same motion
    # intrinsics at (ref_width, ref_height); scaled to the output size. None = the format's default
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    ref_width: int = 640
    ref_height: int = 480


@dataclass
class RenderConfig:
    """RGB appearance."""

    ambient: float = 0.35
    diffuse: float = 0.55
    fill: float = 0.2                            # camera-side fill light
    texture: float = 0.12                        # procedural texture contrast
    rgb_noise: float = 3.0                       # sensor noise std (8-bit levels)
    jpeg_quality: int = 92


@dataclass
class DepthConfig:
    """Kinect-like depth noise and holes (GFIE .npy, CAD-120 PNG; GAFA has no depth)."""

    sigma0: float = 0.0012                       # noise std = sigma0 + sigma_z2 * (z - z0)^2 (m)
    sigma_z2: float = 0.0019
    z0: float = 0.4
    min_range: float = 0.5                       # nearer returns are dropped (m)
    max_range: float = 5.5                       # farther returns are dropped (m)
    edge_threshold: float = 0.04                 # relative depth jump marking an edge pixel
    edge_width: int = 1                          # edge band half width (px at 640 wide)
    edge_hole_prob: float = 0.6
    dark_threshold: float = 0.08                 # albedo luminance below which a surface is dark
    dark_hole_prob: float = 0.5
    shiny_hole_prob: float = 0.5
    blob_rate: float = 1.5                       # random dropout blobs per frame (Poisson mean)
    blob_radius: tuple[float, float] = (3.0, 14.0)  # px at 640 wide
    quantize_mm: bool = True
    head_hole_prob: float = 0.0                  # frames whose whole head box has no depth (dark hair, a sensor hole)


@dataclass
class KeypointConfig:
    """GAFA's OpenPose-like 2D keypoints."""

    noise_px: float = 2.0                        # std at 640 wide
    miss_prob: float = 0.03                      # random undetected joints
    confidence: tuple[float, float] = (0.4, 0.95)


@dataclass
class SynthConfig:
    """All knobs of the synthetic world."""

    room: RoomConfig = field(default_factory=RoomConfig)
    objects: ObjectConfig = field(default_factory=ObjectConfig)
    person: PersonConfig = field(default_factory=PersonConfig)
    gaze: GazeConfig = field(default_factory=GazeConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    keypoints: KeypointConfig = field(default_factory=KeypointConfig)

    @classmethod
    def for_format(cls, fmt: str) -> SynthConfig:
        """The defaults of one dataset format."""
        if fmt not in FORMATS:
            raise ConfigError(f"unknown synthetic format {fmt!r}; choose one of {', '.join(FORMATS)}")
        cfg = cls()
        if fmt == "cad120":
            cfg.person.postures = {"standing": 0.4, "sitting": 0.6, "walking": 0.0}
        elif fmt == "gafa":
            cfg.person.postures = {"standing": 0.25, "sitting": 0.0, "walking": 0.75}
            cfg.person.frame_dt = 1.0 / 15.0
            cfg.gaze.target_mix = {"object": 0.55, "space": 0.25, "out_of_view": 0.20}
            cfg.gaze.dwell = (0.6, 3.0)
            cfg.camera.count = (2, 4)
            cfg.camera.distance = (2.5, 6.0)
            cfg.camera.height = (1.5, 3.0)
            cfg.camera.yaw_offset = 10.0
            # GAFA's intrinsics (the dataset's intrinsics.npz, one K for all cameras), at the 2*cx x 2*cy frame
            # its principal point implies
            cfg.camera.fx, cfg.camera.fy = 1423.7917017, 1427.3147532
            cfg.camera.cx, cfg.camera.cy = 1307.9228078, 1015.3387148
            cfg.camera.ref_width, cfg.camera.ref_height = 2616, 2031
        return cfg

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _merge(obj: Any, override: dict, where: str) -> None:
    """Set the fields of dataclass `obj` from `override`, recursing into sub-dataclasses."""
    if not isinstance(override, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(override).__name__}")
    names = {f.name: f for f in dataclasses.fields(obj)}
    for key, value in override.items():
        if key not in names:
            raise ConfigError(f"{where}.{key}: unknown key; known keys: {', '.join(names)}")
        cur = getattr(obj, key)
        if dataclasses.is_dataclass(cur):
            _merge(cur, value, f"{where}.{key}")
        elif isinstance(cur, tuple):
            if not isinstance(value, (list, tuple)) or (cur and len(value) != len(cur) and key != "shapes"):
                raise ConfigError(f"{where}.{key}: expected a list like {list(cur)}, got {value!r}")
            setattr(obj, key, tuple(value))
        elif isinstance(cur, dict):
            if not isinstance(value, dict):
                raise ConfigError(f"{where}.{key}: expected a mapping like {cur}, got {value!r}")
            setattr(obj, key, {str(k): float(v) for k, v in value.items()})
        elif isinstance(cur, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"{where}.{key}: expected true or false, got {value!r}")
            setattr(obj, key, value)
        else:
            try:
                setattr(obj, key, type(cur)(value))
            except (TypeError, ValueError):
                raise ConfigError(f"{where}.{key}: expected a {type(cur).__name__}, got {value!r}") from None


def _check_mix(mix: dict[str, float], allowed: tuple[str, ...], where: str) -> None:
    bad = set(mix) - set(allowed)
    if bad:
        raise ConfigError(f"{where}: unknown entries {sorted(bad)}; allowed: {', '.join(allowed)}")
    if any(v < 0 for v in mix.values()) or sum(mix.values()) <= 0:
        raise ConfigError(f"{where}: weights must be >= 0 with a positive sum, got {mix}")


def validate(cfg: SynthConfig) -> SynthConfig:
    """Raise ConfigError naming the key of any inconsistent value."""
    for section in dataclasses.fields(cfg):
        sub = getattr(cfg, section.name)
        for f in dataclasses.fields(sub):
            v = getattr(sub, f.name)
            if isinstance(v, tuple) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v) and v[0] > v[1]:
                raise ConfigError(f"{section.name}.{f.name}: range {list(v)} has low > high")
    _check_mix(cfg.gaze.target_mix, TARGET_KINDS, "gaze.target_mix")
    _check_mix(cfg.person.postures, POSTURES, "person.postures")
    bad = set(cfg.objects.shapes) - set(SHAPES)
    if bad or not cfg.objects.shapes:
        raise ConfigError(f"objects.shapes: unknown {sorted(bad)}; allowed: {', '.join(SHAPES)}")
    if cfg.objects.count[0] < 0 or cfg.objects.size[0] <= 0:
        raise ConfigError("objects.count and objects.size must be positive")
    if not 0.0 <= cfg.objects.clustering <= 1.0:
        raise ConfigError(f"objects.clustering must be in [0, 1], got {cfg.objects.clustering}")
    if cfg.camera.count[0] < 1:
        raise ConfigError("camera.count must be at least 1")
    if cfg.person.frame_dt <= 0:
        raise ConfigError("person.frame_dt must be positive")
    return cfg


@dataclass(frozen=True)
class Preset:
    """A named world (`presets/<name>.yaml`): its format, the offset added to the master seed (so
    its rooms are not those of a world of the same seed), a one-line description, and config
    sections applied on top of the format's defaults."""

    name: str
    format: str
    seed_offset: int
    description: str
    sections: dict[str, Any]


PRESET_KEYS = ("format", "seed_offset", "description")


def preset_names() -> list[str]:
    """Names of the presets shipped in ga3ce_prep/synthetic/presets/, sorted."""
    folder = resources.files(__package__) / "presets"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def load_preset(name: str) -> Preset:
    """The preset `name`; ConfigError naming the known presets, or the bad key, otherwise."""
    names = preset_names()
    if name not in names:
        raise ConfigError(f"unknown synthetic preset {name!r}; known presets: {', '.join(names)}")
    where = f"preset {name}"
    data = load_yaml((resources.files(__package__) / "presets" / f"{name}.yaml").read_text()) or {}
    if data.get("format") not in FORMATS:
        raise ConfigError(f"{where}.format: {data.get('format')!r} is not one of {', '.join(FORMATS)}")
    sections = {k: v for k, v in data.items() if k not in PRESET_KEYS}
    _merge(SynthConfig.for_format(data["format"]), sections, where)  # unknown keys are refused here
    return Preset(name, data["format"], int(data.get("seed_offset", 0)), str(data.get("description", "")), sections)


def load_config(fmt: str, path: str | Path | None = None, overrides: dict | None = None,
                preset: str | None = None) -> SynthConfig:
    """The format's defaults, overridden by the preset's sections (`load_preset`; its format must
    be `fmt`), then by the YAML file at `path` (sections as in SynthConfig), then by the mapping
    `overrides` (same layout; used by tests and scripts)."""
    cfg = SynthConfig.for_format(fmt)
    if preset is not None:
        pr = load_preset(preset)
        if pr.format != fmt:
            raise ConfigError(f"preset {preset} writes the {pr.format} format, not {fmt}")
        _merge(cfg, pr.sections, f"preset {preset}")
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"synthetic config {path} not found")
        try:
            data = load_yaml(path.read_text()) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"cannot parse {path}: {e}") from e
        _merge(cfg, data, str(path))
    if overrides:
        _merge(cfg, overrides, "overrides")
    return validate(cfg)
