"""GA3CE (CVPR 2025) in torch: the egocentric transform, D3 encoding, the 3D gaze transformer and
the MLP head, one concept per module under its paper name (docs/paper.md)."""
from .egocentric import EgocentricContext, egocentric_transform, pose_normalization
from .encoding import ENCODINGS, PointEncoding, d3_encoding, fourier_features
from .ga3ce import GA3CE, ModelConfig, model_label
from .loss import angular_loss
from .methods import ALIASES, DEFAULT_METHOD, METHODS, Method, resolve
from .rotation import ROTATIONS, axis_angle_rotation, cyclotorsion_rotation, identity_rotation, rotation
from .transformer import GazeTransformer, MLPHead, gaze_cone_bias

__all__ = [
    "EgocentricContext", "egocentric_transform", "pose_normalization", "ENCODINGS", "PointEncoding",
    "d3_encoding", "fourier_features", "GA3CE", "ModelConfig", "angular_loss", "ALIASES", "DEFAULT_METHOD",
    "METHODS", "Method", "resolve", "model_label", "ROTATIONS",
    "axis_angle_rotation", "cyclotorsion_rotation", "identity_rotation", "rotation",
    "GazeTransformer", "MLPHead", "gaze_cone_bias",
]
