"""Shared test settings (one thread pool sized to the machine) and the shared synthetic worlds."""
import os

for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(var, "2")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from ga3ce_prep.synthetic.generate import generate  # noqa: E402
from ga3ce_prep.testing.worlds import SMALL_WORLD, WORLD_640  # noqa: E402


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
