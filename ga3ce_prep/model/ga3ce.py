"""GA3CE: the full model from the store's per-frame inputs to the gaze direction g.

    v, P_pose, P_object, t_object --egocentric_transform--> v', P'_pose, P'_obj
    E_view = gamma(v') (106),  E_pose = D3 per joint (15 x 10),  E_subject = E_view ++ E_pose (256)
    F_object = D3(P'_obj) (256 each), after a learned null token
    output "regress" (the paper's, the default; method "ga3ce"):
        g' = MLP(decoder(E_subject | encoder(F_object), gaze-cone bias)),  g = normalise(R^T g' + v)
    output "pointer" (designs "pointer-joint", "pointer-frozen"; `ours` today; docs/training.md "The output"):
        g0' = MLP(decoder(E_subject | encoder(null token))),  g0 = normalise(R^T g0' + v)
        p = softmax(q(E_subject) . k([null, F_object]) + kappa (cos(g0, u_i) - 1)),  g = p_null g0 + sum p_i u_i

`ModelConfig` holds every architectural choice and ablation switch, and the fixed name of the design
(model/methods.py) it was made from; it is a plain dataclass saved in checkpoints as a dict.
Units: metres, camera frame (x right, y down, z forward).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
from torch import nn

from ..skeleton import GA3CE_JOINTS, HEAD_WIDTH_PAIR
from .egocentric import egocentric_transform
from .encoding import ENCODINGS, PointEncoding
from .methods import ALIASES, DEFAULT_METHOD, METHODS, NO_OBJECTS_LABEL, aliases_of, resolve, saved_design
from .rotation import ROTATIONS
from .transformer import GazeTransformer, MLPHead, ObjectPointer, gaze_cone_bias

OUTPUTS: tuple[str, ...] = ("pointer", "regress")
POINTER_G0: tuple[str, ...] = ("joint", "frozen")


@dataclass
class ModelConfig:
    """Architecture, encodings and ablation switches of GA3CE; defaults are the paper's values, or
    our reading where it is silent (docs/training.md, "The model"). `for_method` builds a named
    method's config."""

    method: str = (
        # the fixed name of the design (model/methods.py) this config was made from: ga3ce
        # (the paper's), pointer-joint or pointer-frozen; an alias (ours) is resolved to the
        # design it names today. It names the model in every table
        DEFAULT_METHOD)

    rotation: str = (
        # egocentric rotation: cyclotorsion (GA3CE's), axis_angle
        # (ablation "no cyclotorsion"), none (ablation "no egocentric transform")
        "cyclotorsion")
    encoding: str = (
        # point encoding: d3 (direction ++ distance) or standard
        # (gamma of the point itself, same widths; ablation "no D3")
        "d3")
    use_pose: bool = True  # False feeds every joint's learned missing-joint embedding (ablation "appearance + objects")
    use_objects: bool = True  # False feeds the learned null object token alone (ablation "appearance + pose")
    use_context: bool = True  # False is "appearance only": g = v, no parameters are used
    output: str = (
        # regress (the paper's: g = R^T MLP(decoder over the objects) + v) or pointer
        # (ours, docs/training.md "The output": a first pass without objects gives g0, then g
        # points at g0 or at an object, transformer.ObjectPointer)
        "regress")
    cone_bias: bool = (
        # the gaze-cone bias: regress adds cos(v, object direction from the head) to cross-attention
        # (the paper); pointer adds pointer_kappa (cos(g0, object direction) - 1) to its logits
        True)
    cone_bias_scale: float = 1.0  # regress: multiplies the paper's gaze-cone bias (1 = the paper)
    pointer_g0: str = (
        # pointer: how g0's network is trained: joint (with the pointer; its arccos loss
        # weighted by TrainConfig.first_pass_loss) or frozen (the no-objects model is
        # trained first, into the run's g0/ folder, then frozen; the pointer trains on top)
        "joint")
    pointer_kappa: float = (
        # pointer: sharpness of the cone around g0 (300: an object 5 degrees off
        # g0 loses 1.1 to the null token, 10 degrees off 4.6; chosen on val)
        300.0)
    d_model: int = 256  # transformer width = E_subject's width, view_width + 15 x joint_width
    n_heads: int = 2  # attention heads
    dim_feedforward: int = 512  # feed-forward width of each transformer layer
    num_encoder_layers: int = 3  # encoder layers over [null token, objects]
    num_decoder_layers: int = 3  # decoder layers over the subject token
    dropout: float = 0.1  # transformer dropout (nn.Transformer's default)
    norm_first: bool = False  # pre-LayerNorm layers; False = nn.Transformer's default, post-LN
    head_hidden: int = 512  # hidden width of the MLP head d_model -> head_hidden -> 3
    view_width: int = 106  # width of gamma(v'): 53 frequencies
    joint_width: int = 10  # width of each joint's encoding
    joint_dir_width: int = 6  # of joint_width, the direction part of D3 (the rest: distance)
    object_dir_width: int = 128  # of d_model, the direction part of each object's D3 (the rest: distance)
    view_scale: float = 1.0  # Fourier scale of gamma(v'), cycles per unit-vector component
    direction_scale: float = (
        # Fourier scale of D3's direction part, cycles per unit-vector component (chosen on val)
        0.25)
    pose_distance_scale: float = 0.05  # Fourier scale of D3's joint distance, cycles per head width
    object_distance_scale: float = 0.3  # Fourier scale of D3's object distance, cycles per metre
    pose_position_scale: float = 0.05  # standard encoding's scale for joints, cycles per head width (chosen on val)
    object_position_scale: float = 0.15  # standard encoding's scale for objects, cycles per metre (chosen on val)
    head_width_pair: tuple[int, int] = (
        # joints whose distance is the head width 1/s of the pose normalisation
        HEAD_WIDTH_PAIR)
    fourier_seed: int = 0  # seed of the fixed Gaussian matrices B of every Fourier encoding

    def __post_init__(self) -> None:
        a, b = self.head_width_pair
        self.head_width_pair = (int(a), int(b))  # JSON gives a list
        if self.method in ALIASES:   # the design the alias names today is what this config is
            self.method = ALIASES[self.method]
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {tuple(METHODS)} (or an alias: {tuple(ALIASES)}), "
                             f"got {self.method!r}")
        if self.rotation not in ROTATIONS:
            raise ValueError(f"rotation must be one of {ROTATIONS}, got {self.rotation!r}")
        if self.output not in OUTPUTS:
            raise ValueError(f"output must be one of {OUTPUTS}, got {self.output!r}")
        if self.pointer_g0 not in POINTER_G0:
            raise ValueError(f"pointer_g0 must be one of {POINTER_G0}, got {self.pointer_g0!r}")
        if self.encoding not in ENCODINGS:
            raise ValueError(f"encoding must be one of {ENCODINGS}, got {self.encoding!r}")
        subject = self.view_width + len(GA3CE_JOINTS) * self.joint_width
        if subject != self.d_model:
            raise ValueError(f"E_subject width {self.view_width} + {len(GA3CE_JOINTS)} x "
                             f"{self.joint_width} = {subject} must equal d_model {self.d_model}")

    @property
    def g0_frozen(self) -> bool:
        """Whether g0's network is the no-objects model, trained first and frozen (pointer_g0)."""
        return self.use_context and self.use_objects and self.output == "pointer" and self.pointer_g0 == "frozen"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["head_width_pair"] = list(self.head_width_pair)
        return d

    @classmethod
    def for_method(cls, name: str = DEFAULT_METHOD, **overrides: Any) -> ModelConfig:
        """Design `name`'s config (model/methods.py; an alias such as `ours` is resolved to the
        design it names today, which the config records), with `overrides` (ablation switches,
        `--model-set`) on top."""
        design = resolve(name)
        return cls(**{**METHODS[design].config, **overrides, "method": design})

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        known = {f.name for f in fields(cls)}
        # configurations saved before the pointer existed are the paper's model; before pointer_g0
        # existed, g0 was trained jointly
        d = {"output": "regress", "pointer_g0": "joint", **d}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown model config keys {sorted(unknown)}")
        if "method" not in d:  # saved before methods had names: the output says which
            d["method"] = "ours" if d["output"] == "pointer" else "ga3ce"
        if d["method"] in ALIASES:   # saved before the fixed names: the design the alias named then
            d["method"] = saved_design(d["method"], {**asdict(cls()), **d})
        return cls(**d)


# the design switches a label names
SWITCHES = ("output", "pointer_g0", "rotation", "encoding", "use_pose", "cone_bias")
APPEARANCE_LABEL = "appearance only (v)"


def model_label(config: ModelConfig) -> str:
    """A config's name in tables: its method's label, or the ablation that leaves the objects or the
    whole context out (the same network whichever method it came from); a design switch that
    differs from the method's own value is named after it ("GA3CE (paper), use_pose=False"). Sizes
    and scales do not rename a model. The design the alias `ours` names today says so:
    "pointer-frozen (ours)"."""
    if not config.use_context:
        return APPEARANCE_LABEL
    if not config.use_objects:
        return NO_OBJECTS_LABEL
    own = type(config).for_method(config.method)
    changed = [f"{k}={getattr(config, k)}" for k in SWITCHES if getattr(config, k) != getattr(own, k)]
    name = METHODS[config.method].label + "".join(f" ({a})" for a in aliases_of(config.method))
    return ", ".join([name, *changed])


class GA3CE(nn.Module):
    """The GA3CE gaze estimator.

    forward(view (B,3) unit, pose (B,30,3) NaN = missing, head_pos (B,3), objects (B,S,3),
    mask (B,S) bool True = real object) -> g (B,3) unit gaze direction, camera frame.
    """

    def __init__(self, config: ModelConfig | None = None):
        super().__init__()
        self.config = c = config or ModelConfig()
        if not c.use_context:
            return
        gen = torch.Generator().manual_seed(c.fourier_seed)
        self.view_encoding = PointEncoding("standard", c.view_width, 0, 0.0, 0.0, c.view_scale, gen)
        self.pose_encoding = PointEncoding(c.encoding, c.joint_width, c.joint_dir_width, c.direction_scale,
                                           c.pose_distance_scale, c.pose_position_scale, gen)
        self.object_encoding = PointEncoding(c.encoding, c.d_model, c.object_dir_width, c.direction_scale,
                                             c.object_distance_scale, c.object_position_scale, gen)
        self.missing_joint = nn.Parameter(0.02 * torch.randn(len(GA3CE_JOINTS), c.joint_width, generator=gen))
        self.transformer = GazeTransformer(c.d_model, c.n_heads, c.dim_feedforward,
                                           c.num_encoder_layers, c.num_decoder_layers, c.dropout, c.norm_first)
        self.head = MLPHead(c.d_model, c.head_hidden)
        if c.output == "pointer" and c.use_objects:  # nothing to point at without objects: no unused weights
            self.pointer = ObjectPointer(c.d_model)

    @property
    def g0_frozen(self) -> bool:
        """ModelConfig.g0_frozen of this model's config."""
        return self.config.g0_frozen

    def train(self, mode: bool = True) -> GA3CE:
        """nn.Module.train; a frozen g0 network stays in eval mode (no dropout: g0 is the no-objects
        model's own estimate)."""
        super().train(mode)
        if mode and self.g0_frozen:
            for name, child in self.named_children():
                if name != "pointer":
                    child.eval()
        return self

    def subject_embedding(self, view_ego: torch.Tensor, pose_ego: torch.Tensor,
                          joint_valid: torch.Tensor) -> torch.Tensor:
        """E_subject (B, 256) = gamma(v') ++ flatten(E_pose); invalid joints get the learned
        missing-joint embedding (all joints when use_pose is off)."""
        e_pose = self.pose_encoding(pose_ego)                              # (B, 15, 10)
        valid = joint_valid if self.config.use_pose else torch.zeros_like(joint_valid)
        e_pose = torch.where(valid[..., None], e_pose, self.missing_joint.expand_as(e_pose))
        return torch.cat([self.view_encoding(view_ego), e_pose.flatten(1)], dim=-1)

    def forward(self, view: torch.Tensor, pose: torch.Tensor, head_pos: torch.Tensor, objects: torch.Tensor,
                mask: torch.Tensor, all_passes: bool = False) -> torch.Tensor | list[torch.Tensor]:
        """g (B, 3); with all_passes the estimates (B, 3) of every pass, g last (for the loss):
        [g0, g] for the pointer output (g0: the first pass, the network without objects), else [g]."""
        passes, _ = self._passes(view, pose, head_pos, objects, mask)
        return passes if all_passes else passes[-1]

    def _passes(self, view: torch.Tensor, pose: torch.Tensor, head_pos: torch.Tensor, objects: torch.Tensor,
                mask: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The passes' estimates (B, 3), g last, and the pointer's weights p (B, 1 + S) over
        [g0, objects] (None for the regress output)."""
        c = self.config
        view = nn.functional.normalize(view, dim=-1)
        if not c.use_context:
            return [view], None
        if not c.use_objects:
            objects, mask = objects[:, :0], mask[:, :0]
        ctx = egocentric_transform(view, pose, objects, head_pos, c.rotation, c.head_width_pair)
        subject = self.subject_embedding(ctx.view, ctx.pose, ctx.joint_valid)
        tokens = self.object_encoding(ctx.objects)
        if c.output == "regress" or not c.use_objects:   # the paper's model; the no-objects ablation of either
            bias = gaze_cone_bias(ctx.view, ctx.objects, mask, c.n_heads, c.cone_bias_scale) if c.cone_bias else None
            return [self._to_camera(ctx.R, self.head(self.transformer(subject, tokens, mask, bias)), view)], None
        # pointer: the first pass sees the null token alone; g points at g0 or at the objects around it
        g0_prime = self.head(self.transformer(subject, tokens[:, :0], mask[:, :0], None))
        axis = nn.functional.normalize(g0_prime + ctx.view, dim=-1, eps=1e-9)            # g0, egocentric
        bias = (gaze_cone_bias(axis.detach(), ctx.objects, mask, 1, c.pointer_kappa, relative=True)[:, 0]
                if c.cone_bias else torch.cat([mask.new_ones(len(mask), 1), mask], 1).float().log())  # -inf = padding
        keys = torch.cat([self.transformer.null_token.expand(len(tokens), 1, -1), tokens], 1)   # [null, F_object]
        g_ego, p = self.pointer(subject, keys, axis, ctx.objects, bias)
        g = nn.functional.normalize(torch.einsum("bji,bj->bi", ctx.R, g_ego), dim=-1, eps=1e-9)
        return [self._to_camera(ctx.R, g0_prime, view), g], p

    def object_weights(self, view: torch.Tensor, pose: torch.Tensor, head_pos: torch.Tensor,
                       objects: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """g (B, 3) and the weight the model gives [null token (g0 for the pointer), objects]
        (B, 1 + S): the pointer's p, or the regress model's last decoder layer's cross-attention
        (mean over heads). Eval mode."""
        if self.config.output == "pointer" and self.config.use_objects and self.config.use_context:
            (*_, g), p = self._passes(view, pose, head_pos, objects, mask)
            assert p is not None  # the pointer output's weights
            return g, p
        g, w = self.cross_attention(view, pose, head_pos, objects, mask)
        return g, w[:, -1].mean(1)

    @staticmethod
    def _to_camera(R: torch.Tensor, g_prime: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
        """g' (B, 3) egocentric, v (B, 3) camera frame -> g = normalise(R^T g' + v) (B, 3)."""
        return nn.functional.normalize(torch.einsum("bji,bj->bi", R, g_prime) + view, dim=-1, eps=1e-9)

    def cross_attention(self, view: torch.Tensor, pose: torch.Tensor, head_pos: torch.Tensor,
                        objects: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """forward's g (B, 3), unchanged, and the decoder's cross-attention weights (B, layers,
        heads, 1 + S) over [null token, objects] (GazeTransformer.record_cross_attention; S = 0
        when use_objects is off or the output is the pointer, whose decoder sees the null token alone).
        Eval mode; the appearance-only model (use_context off) has none."""
        if not self.config.use_context:
            raise ValueError("this model has no attention: use_context is off (the appearance-only row, g = v)")
        with self.transformer.record_cross_attention() as record:
            g = self(view, pose, head_pos, objects, mask)
        return g, torch.stack(record, dim=1)
