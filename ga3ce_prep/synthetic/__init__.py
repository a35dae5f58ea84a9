"""The synthetic RGB-D world: rooms with furniture and objects, a person on the smpl+head_30
skeleton looking at targets, Kinect/surveillance-like cameras, written in the GFIE, CAD-120 or
GAFA on-disk format with an exact truth side-car (truth.h5). See docs/synthetic.md.

Modules, one concept each: config (knobs), meshes, room, person, gaze (head/body follow), targets,
camera, render, noise, world (scene and timeline), truth (side-car), writers (formats), generation
(`generate`), cli.
"""
from .config import SynthConfig, load_config
from .truth import TruthFrame, TruthReader

__all__ = ["SynthConfig", "TruthFrame", "TruthReader", "generate", "load_config"]


def generate(*args, **kwargs):
    """See ga3ce_prep.synthetic.generation.generate (imported lazily: it loads Open3D). The module is
    not named `generate`: importing it would replace this function on the package."""
    from .generation import generate as _generate

    return _generate(*args, **kwargs)
