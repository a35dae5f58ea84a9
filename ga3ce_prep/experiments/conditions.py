"""The conditions a figure was measured under, recorded beside it: the machine and the code.

Training repeats bit for bit on one machine type, vector unit and thread count, not across them
(docs/studies/2026-12-06-figures-across-cpus.md): torch's kernels follow the CPU's vector unit, and
twenty epochs turn their last-bit differences into other weights. So every results file names them.
"""
from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any


def cpu_name() -> str:
    """The CPU's model name ("Intel(R) Xeon(R) Processor", "AMD EPYC 7B13"), from /proc/cpuinfo where
    there is one."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """The machine a figure came from: CPU model, torch's kernel level (`ATEN_CPU_CAPABILITY`'s
    values: default, avx2, avx512), cores, torch's threads, and the numeric libraries' versions."""
    import numpy
    import torch

    return {"cpu": cpu_name(), "vector_unit": torch.backends.cpu.get_cpu_capability().lower(),
            "cores": os.cpu_count(), "threads": torch.get_num_threads(), "cuda": torch.cuda.is_available(),
            "python": platform.python_version(), "torch": torch.__version__, "numpy": numpy.__version__}


def code() -> dict[str, Any]:
    """The code a figure came from: the package version and, in a git checkout, its commit and
    whether the tree had uncommitted changes."""
    from .. import __version__

    out: dict[str, Any] = {"version": __version__, "commit": None, "dirty": None}
    here = Path(__file__).resolve().parents[2]
    try:
        out["commit"] = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                                       check=True, timeout=10).stdout.strip() or None
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                capture_output=True, text=True, check=True, timeout=10).stdout
        out["dirty"] = bool(status.strip())
    except (OSError, subprocess.SubprocessError):
        pass  # an installed wheel: the version says it
    return out


def describe(m: dict[str, Any]) -> str:
    """One line for a printed table: "Intel(R) Xeon(R) Processor, torch kernels avx512, 2 threads"."""
    return f"{m['cpu']}, torch kernels {m['vector_unit']}, {m['threads']} threads"
