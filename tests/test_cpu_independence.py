"""No test's truth is one CPU's last bits: the random-weight MobileSAM files build to the same digests
under every vector-unit level this CPU can run (testing/cpu_levels.py: torch, MKL, oneDNN and numpy
each held to it in a child process), and their checks are ones an AVX2 or an older CPU also passes."""
import os
import subprocess
import sys

import pytest

from ga3ce_prep.testing import mobilesam_random
from ga3ce_prep.testing.cpu_levels import LEVELS, level_env, levels_here, numpy_dispatch


@pytest.mark.parametrize("level", levels_here())
def test_test_models_build_alike_on_every_vector_unit(tmp_path, level):
    """The export run as a CPU of `level` runs it gives the digests `verify` holds; the encoder's
    fingerprint (ONNX Runtime, here) then stands within its tolerance."""
    mobilesam_random.ensure()  # the code folder installed, once
    env = {**os.environ, **level_env(level)}
    subprocess.run([sys.executable, "-W", "ignore", "-m", "ga3ce_prep.testing.mobilesam_random", "--export",
                    str(tmp_path)], check=True, env=env, stdout=subprocess.DEVNULL)
    assert mobilesam_random.decoder_digest(tmp_path / mobilesam_random.DECODER) == mobilesam_random.DECODER_DIGEST
    assert mobilesam_random.checkpoint_digest(tmp_path / mobilesam_random.CHECKPOINT) == \
        mobilesam_random.CHECKPOINT_DIGEST
    mobilesam_random.verify(tmp_path)


def test_levels_hold_a_child_process_to_them():
    """The environment really lowers torch's and numpy's kernels in the child (else the test above
    would prove nothing)."""
    code = ("import torch; from numpy._core import _multiarray_umath as m; "
            "print(torch.backends.cpu.get_cpu_capability().lower(), "
            "sum(bool(m.__cpu_features__[f]) for f in m.__cpu_dispatch__))")
    seen = {}
    for level in levels_here():
        out = subprocess.run([sys.executable, "-c", code], env={**os.environ, **level_env(level)},
                             check=True, capture_output=True, text=True).stdout.split()
        seen[level] = (out[0], int(out[1]))
    assert [s[0] for s in seen.values()] == levels_here()
    assert seen["default"][1] == 0                                 # no numpy dispatch target left
    assert [s[1] for s in seen.values()] == sorted(s[1] for s in seen.values())
    with pytest.raises(ValueError, match="one of"):
        level_env("sse")
    assert LEVELS[0] == "default"


def test_a_level_is_named_from_the_build_not_from_the_callers_cap(monkeypatch):
    """Under a parent already held to a level (its own NPY_DISABLE_CPU_FEATURES), `default` still
    turns every numpy dispatch target off, and a child never gets back what its parent left off."""
    monkeypatch.setenv("NPY_DISABLE_CPU_FEATURES", "X86_V4 AVX512_ICL")
    off = level_env("default")["NPY_DISABLE_CPU_FEATURES"].split()
    assert set(numpy_dispatch()[0]) <= set(off) and {"X86_V4", "AVX512_ICL"} <= set(off)
    assert {"X86_V4", "AVX512_ICL"} <= set(level_env("avx512").get("NPY_DISABLE_CPU_FEATURES", "").split())
