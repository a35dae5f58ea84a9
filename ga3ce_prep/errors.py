"""Error classes. Each message names the file or key at fault and the fix."""
from __future__ import annotations

import traceback
from pathlib import Path

DEBUG_HINT = "rerun with GA3CE_DEBUG=1 for the traceback"


def where_raised(e: BaseException) -> str:
    """"<file>:<line>" of the innermost frame an unexpected exception was raised in ("" if unknown),
    for the one-line messages that stand in for a traceback."""
    tb = traceback.extract_tb(e.__traceback__)
    return f"{Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""


class Ga3ceError(Exception):
    """Base class: the CLI prints these as one clear message, without a traceback."""


class DatasetFormatError(Ga3ceError):
    """A structural problem with a dataset on disk (layout, annotation columns): stops a run before any work."""


class FrameError(Ga3ceError):
    """A problem with one frame (missing image, no depth at the head): becomes a failure record."""


class ConfigError(Ga3ceError):
    """A pipeline file or option is invalid."""


class ModelFileError(Ga3ceError):
    """A model file is missing or does not match the interface it should have."""


class StoreError(Ga3ceError):
    """A store is missing, incomplete, locked or of another schema version."""
