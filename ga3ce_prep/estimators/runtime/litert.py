"""TensorFlow Lite models (MediaPipe's BlazePose, BlazeFace, face mesh) through LiteRT
(`ai-edge-litert`, TensorFlow's standalone runtime): interpreters with a thread count, the check of
a file's inputs and outputs against the contract a runner expects, and one call.

The models run on the CPU (XNNPACK). LiteRT has no CUDA path in its Python package; GPU users run
the ONNX backends instead (docs/models/registry.md, "Which model, where").
"""
from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import ModelFileError
from ...params import param


@dataclass(frozen=True, kw_only=True)
class LiteParams:
    """How a LiteRT estimator runs: every TFLite backend's parameters include these."""

    threads: int = param(
        # LiteRT (XNNPACK) threads per interpreter; these models are small, so 1 thread and dask workers for parallelism
        1, minimum=1)


@dataclass(frozen=True)
class LiteTensor:
    """One input or output of a TFLite model contract: name and shape (None = any size)."""

    name: str
    shape: tuple[int | None, ...]


class LiteModel:
    """One TFLite file behind a lock (an interpreter is not thread-safe).

    `LiteModel(path, inputs, outputs, threads, what)` checks the file's tensors against the
    contract (names and fixed dims) and refuses a mismatch naming the file, the tensor, and the
    expected and found shapes. `model(x)` runs the single input x and returns the outputs by name
    (float32 arrays)."""

    def __init__(self, path: str | Path, inputs: Sequence[LiteTensor], outputs: Sequence[LiteTensor],
                 threads: int = LiteParams.threads, what: str = "model"):
        from ai_edge_litert.interpreter import Interpreter

        self.path, self.what = Path(path), what
        if not self.path.is_file():
            raise ModelFileError(f"{what} TFLite file not found: {self.path}")
        try:
            self.interpreter = Interpreter(model_path=str(self.path), num_threads=int(threads))
            self.interpreter.allocate_tensors()
        except (ValueError, RuntimeError) as e:
            raise ModelFileError(f"cannot load {what} TFLite {self.path}: {e}") from e
        self._lock = threading.Lock()
        ins = {d["name"]: d for d in self.interpreter.get_input_details()}
        outs = {d["name"]: d for d in self.interpreter.get_output_details()}
        for kind, specs, found in (("input", inputs, ins), ("output", outputs, outs)):
            for spec in specs:
                d = found.get(spec.name)
                if d is None:
                    raise ModelFileError(f"{what} TFLite {self.path}: no {kind} named {spec.name!r}; expected "
                                         f"{[s.name for s in specs]}, found {list(found)}")
                dims = tuple(int(x) for x in d["shape"])
                if len(dims) != len(spec.shape) or any(e is not None and e != f for e, f in zip(spec.shape, dims)):
                    raise ModelFileError(f"{what} TFLite {self.path}: {kind} {spec.name!r} expected shape "
                                         f"{list(spec.shape)}, found {list(dims)}")
        self._input = ins[inputs[0].name]["index"]
        self._outputs = {s.name: outs[s.name]["index"] for s in outputs}

    def __call__(self, x: np.ndarray) -> dict[str, np.ndarray]:
        with self._lock:
            self.interpreter.set_tensor(self._input, np.ascontiguousarray(x, np.float32))
            self.interpreter.invoke()
            return {name: self.interpreter.get_tensor(i).copy() for name, i in self._outputs.items()}

    def __getstate__(self):  # interpreters stay in the process that made them (dask workers rebuild)
        raise TypeError("LiteModel holds a native interpreter; build it in the worker (Backend.warm)")
