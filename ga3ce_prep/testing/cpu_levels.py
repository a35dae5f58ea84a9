"""The CPU's vector-unit levels, and the environment that holds a child process to one of them: how
the tests show that a digest or golden value is the same on every CPU without a second machine.

torch (`ATEN_CPU_CAPABILITY`), MKL (`MKL_ENABLE_INSTRUCTIONS`), oneDNN (`ONEDNN_MAX_CPU_ISA`) and
numpy (`NPY_DISABLE_CPU_FEATURES`) each pick their kernels by the vector unit, and each reads an
environment variable that caps it, at process start. An Intel CPU with AVX-512 can so run as an
AVX2 machine (most AMD EPYCs) and as one with neither. ONNX Runtime reads no such variable: its
kernels are checked by the spread the tests allow instead (testing/mobilesam_random.py).

    levels_here()           # ['default', 'avx2', 'avx512'] on an AVX-512 CPU
    level_env('avx2')       # {'ATEN_CPU_CAPABILITY': 'avx2', 'MKL_ENABLE_INSTRUCTIONS': 'AVX2', ...}
"""
from __future__ import annotations

LEVELS = ("default", "avx2", "avx512")
# per level: MKL's and oneDNN's names of the same cap
_MKL = {"default": "SSE4_2", "avx2": "AVX2", "avx512": "AVX512"}
_ONEDNN = {"default": "SSE41", "avx2": "AVX2", "avx512": "AVX512_CORE"}


def levels_here() -> list[str]:
    """The levels this CPU can run, lowest first: `LEVELS` up to torch's own choice here."""
    import torch

    top = torch.backends.cpu.get_cpu_capability().lower()
    return list(LEVELS[: LEVELS.index(top) + 1]) if top in LEVELS else ["default"]


def numpy_dispatch() -> tuple[list[str], dict[str, bool]]:
    """numpy's build-time dispatch targets and which features this process runs with."""
    import importlib

    try:
        um = importlib.import_module("numpy._core._multiarray_umath")
    except ImportError:  # numpy 1.x
        um = importlib.import_module("numpy.core._multiarray_umath")
    return list(um.__cpu_dispatch__), dict(um.__cpu_features__)


def _numpy_features_above(level: str) -> list[str]:
    """numpy's dispatch targets (as this numpy's build names them: X86_V3 / X86_V4 in numpy 2.4,
    AVX2 / AVX512F / AVX512_SKX before) that a CPU of `level` would lack, after those this process
    was already told to leave off (its own NPY_DISABLE_CPU_FEATURES: a child never runs above its
    parent). Named from the build's list, not from what this process has on, so the answer does
    not depend on the caller's own cap."""
    import os

    targets = list(numpy_dispatch()[0])
    off = (targets if level == "default" else
           [f for f in targets if "512" in f or f == "X86_V4"] if level == "avx2" else [])
    inherited = os.environ.get("NPY_DISABLE_CPU_FEATURES", "").replace(",", " ").split()
    return list(dict.fromkeys([*inherited, *off]))


def level_env(level: str) -> dict[str, str]:
    """Environment variables that hold torch, MKL, oneDNN and numpy in a new process to `level`
    (one of `LEVELS`); add them to a copy of `os.environ`."""
    if level not in LEVELS:
        raise ValueError(f"level {level!r}: one of {', '.join(LEVELS)}")
    env = {"ATEN_CPU_CAPABILITY": level, "MKL_ENABLE_INSTRUCTIONS": _MKL[level], "ONEDNN_MAX_CPU_ISA": _ONEDNN[level]}
    numpy_off = _numpy_features_above(level)
    if numpy_off:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(numpy_off)
    return env
