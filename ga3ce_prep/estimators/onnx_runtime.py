"""ONNX Runtime sessions shared by every ONNX estimator: execution providers, thread counts, and the
check of a model file's inputs and outputs against the interface the runner expects."""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import onnxruntime as ort

from ..errors import ConfigError, ModelFileError
from ..params import param

Dim = int | str | None  # int: that size; str: any size (a named, dynamic axis); None: any size


@dataclass(frozen=True)
class TensorSpec:
    """One input or output of a model contract. dtype is ONNX Runtime's type string."""

    name: str
    shape: tuple[Dim, ...]
    dtype: str = "tensor(float)"


@dataclass(frozen=True, kw_only=True)
class RuntimeParams:
    """How an ONNX estimator runs: every ONNX backend's parameters include these."""

    providers: str = "cpu"  # ONNX Runtime execution providers in preference order, comma-separated: cpu, cuda (needs onnxruntime-gpu), tensorrt, or full provider names
    threads: int = param(2, minimum=1)  # intra-op threads per ONNX Runtime session


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file (model provenance)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def resolve_providers(providers: str | Sequence[str] | None) -> list[str]:
    """Execution providers in preference order, checked against this onnxruntime build.

    "cpu" / "cuda" / "tensorrt" / "coreml" / "dml" are shorthands; CPUExecutionProvider is always
    appended as the fallback. Raises ConfigError naming the missing provider and the package to
    install (onnxruntime-gpu for CUDA)."""
    short = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider",
             "tensorrt": "TensorrtExecutionProvider", "coreml": "CoreMLExecutionProvider",
             "dml": "DmlExecutionProvider"}
    if providers is None:
        providers = ["cpu"]
    if isinstance(providers, str):
        providers = [p.strip() for p in providers.split(",") if p.strip()]
    wanted = [short.get(p.lower(), p) for p in providers]
    available = ort.get_available_providers()
    for p in wanted:
        if p not in available:
            hint = (" Install the GPU build: pip uninstall onnxruntime && pip install onnxruntime-gpu"
                    if p in ("CUDAExecutionProvider", "TensorrtExecutionProvider") else "")
            raise ConfigError(f"execution provider {p} is not available in this onnxruntime build "
                              f"(available: {', '.join(available)}).{hint}")
    if "CPUExecutionProvider" not in wanted:
        wanted.append("CPUExecutionProvider")
    return wanted


def session_options(threads: int) -> ort.SessionOptions:
    """Session options: `threads` intra-op threads, one inter-op thread, every graph optimisation."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    return so


def create_session(model: str | Path | bytes, providers: Sequence[str], threads: int,
                   what: str = "model", disabled_optimizers: Sequence[str] = ()) -> ort.InferenceSession:
    """An InferenceSession on a file path or serialized bytes; a missing or unreadable file raises
    ModelFileError naming it.

    providers: resolved execution providers in preference order (`resolve_providers`).
    threads: intra-op threads (`RuntimeParams.threads` holds the default).
    disabled_optimizers: ORT graph transformers to skip by name."""
    if not isinstance(model, bytes):
        path = Path(model)
        if not path.is_file():
            raise ModelFileError(f"{what} ONNX file not found: {path}")
        model = str(path)
    try:
        return ort.InferenceSession(model, session_options(threads), providers=list(providers),
                                    disabled_optimizers=list(disabled_optimizers) or None)
    except Exception as e:  # noqa: BLE001 - onnxruntime raises its own exception types
        where = model if isinstance(model, str) else "(in memory)"
        raise ModelFileError(f"cannot load {what} ONNX {where}: {e}") from e


def _dims(arg) -> tuple[Dim, ...]:
    return tuple(d if isinstance(d, int) else (d or None) for d in (arg.shape or []))


def _fmt(shape: Sequence[Dim]) -> str:
    return "[" + ", ".join("?" if d is None else str(d) for d in shape) + "]"


def check_contract(sess: ort.InferenceSession, inputs: Sequence[TensorSpec], outputs: Sequence[TensorSpec],
                   path: str | Path, what: str) -> None:
    """Refuse a model whose inputs or outputs differ from the contract.

    Names must match; ranks must match; a fixed contract dimension must equal the file's (a dynamic
    axis in the file is accepted: it takes the size we feed); dtypes must match. The error names the
    file, the tensor, and the expected and found shapes."""
    for kind, specs, args in (("input", inputs, sess.get_inputs()), ("output", outputs, sess.get_outputs())):
        found = {a.name: a for a in args}
        for spec in specs:
            if spec.name not in found:
                raise ModelFileError(f"{what} ONNX {path}: no {kind} named {spec.name!r}; expected "
                                     f"{[s.name for s in specs]}, found {list(found)}")
            a = found[spec.name]
            dims = _dims(a)
            bad_rank = len(dims) != len(spec.shape)
            bad_dim = not bad_rank and any(isinstance(e, int) and isinstance(f, int) and e != f
                                           for e, f in zip(spec.shape, dims))
            if bad_rank or bad_dim:
                raise ModelFileError(f"{what} ONNX {path}: {kind} {spec.name!r} expected shape {_fmt(spec.shape)}, "
                                     f"found {_fmt(dims)}")
            if a.type != spec.dtype:
                raise ModelFileError(f"{what} ONNX {path}: {kind} {spec.name!r} expected type {spec.dtype}, "
                                     f"found {a.type}")


def input_dims(sess: ort.InferenceSession, name: str) -> tuple[Dim, ...]:
    """The declared dims of one input (ints, or None for a dynamic axis)."""
    for a in sess.get_inputs():
        if a.name == name:
            return tuple(d if isinstance(d, int) else None for d in a.shape)
    raise KeyError(name)
