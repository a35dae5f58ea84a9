"""Shared test settings (one thread pool sized to the machine) and the shared synthetic worlds."""
import os

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "2")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from ga3ce_prep.synthetic import generate  # noqa: E402
from ga3ce_prep.testing.worlds import GAFA_GAP, GAFA_WORLD, SMALL_WORLD, WORLD_640  # noqa: E402


@pytest.fixture(scope="session")
def synth_world(tmp_path_factory) -> Path:
    """A 160x120 synthetic GFIE-format world (3 scenes x 4 frames) with its truth.h5."""
    root = tmp_path_factory.mktemp("synth") / "gfie"
    generate("gfie", root, progress=False, **SMALL_WORLD)
    return root


@pytest.fixture(scope="session")
def synth_world_640(tmp_path_factory) -> Path:
    """A 640x480 synthetic GFIE-format world (4 scenes x 2 frames), the benchmark's resolution."""
    root = tmp_path_factory.mktemp("synth640") / "gfie"
    generate("gfie", root, progress=False, **WORLD_640)
    return root


@pytest.fixture(scope="session")
def synth_gafa_world(tmp_path_factory) -> Path:
    """A 160-px GAFA-format world (GAFA_WORLD: 6 camera sequences of raw frames 0-9) with a gap: the
    keypoints of raw frame GAFA_GAP[1] of camera GAFA_GAP[0] are zeroed, so the adapter skips it as
    GAFA skips frames with no head joint."""
    import pickle

    root = tmp_path_factory.mktemp("synthgafa") / "gafa"
    generate("gafa", root, progress=False, **GAFA_WORLD)
    pkl = root / f"{GAFA_GAP[0]}.pkl"
    d = pickle.loads(pkl.read_bytes())
    d["keypoints2d"][GAFA_GAP[1]] = 0
    pkl.write_bytes(pickle.dumps(d, protocol=4))
    return root
