"""A restricted unpickler for dataset pickles (GAFA's per-camera .pkl files).

`pickle.load` on a downloaded file can run arbitrary code. `load_pickle` admits only what
annotation files need: built-in containers and scalars, numpy arrays, dtypes and scalars. Any
other global in the stream is refused with the file and the name it asked for.
"""
from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

from ..errors import DatasetFormatError

_ALLOWED: set[tuple[str, str]] = {
    ("builtins", "dict"), ("builtins", "list"), ("builtins", "tuple"), ("builtins", "set"),
    ("builtins", "frozenset"), ("builtins", "bytearray"), ("builtins", "complex"),
    ("builtins", "slice"), ("collections", "OrderedDict"),
    ("_codecs", "encode"),  # protocol-2 pickles of numpy arrays encode their bytes with it
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
}
_NUMPY_DTYPE_MODULES = ("numpy", "numpy.dtypes")


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _ALLOWED or (module in _NUMPY_DTYPE_MODULES and name.endswith("DType")):
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"global '{module}.{name}' is not allowed")


def load_pickle(path: str | Path) -> Any:
    """Unpickle `path` admitting only containers, scalars and numpy arrays."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return _RestrictedUnpickler(f).load()
    except pickle.UnpicklingError as e:
        raise DatasetFormatError(f"{path}: refused to unpickle: {e}. Annotation pickles may hold only "
                                 "dicts, lists and numpy arrays") from e
    except (OSError, EOFError, ValueError) as e:
        raise DatasetFormatError(f"cannot read pickle {path}: {e}") from e
