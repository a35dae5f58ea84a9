"""The adapter contract."""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path

from ..errors import DatasetFormatError
from ..frames import FrameRef


class DatasetAdapter(ABC):
    """Reads one dataset format. `frames()` yields FrameRefs in a stable order (same dataset, same
    order and ids); structural problems raise DatasetFormatError when the adapter is built."""

    name: str = ""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetFormatError(f"dataset root {self.root} is not a directory")

    @abstractmethod
    def frames(self) -> Iterator[FrameRef]:
        """All frames of the dataset, every split."""

    def __iter__(self) -> Iterator[FrameRef]:
        return self.frames()
