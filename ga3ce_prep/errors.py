"""Error classes. Each message names the file or key at fault and the fix."""
from __future__ import annotations

import errno
import shutil
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


class EnvironmentProblem(Ga3ceError):
    """The machine refused what a command needed (a full disk, a permission, a read-only or lost
    filesystem, a path too long): not a bug. Made by `environment_problem`, the one place that
    tells such an OSError from a bug."""


# errno -> what the machine said, and the fix that belongs to it
_ENVIRONMENT: dict[int, tuple[str, str]] = {
    errno.ENOSPC: ("no space left on its filesystem", "free space there"),
    errno.EDQUOT: ("the disk quota is exceeded", "free space within your quota there"),
    errno.EACCES: ("permission denied", "give this user write access there"),
    errno.EPERM: ("operation not permitted", "give this user write access there"),
    errno.EROFS: ("its filesystem is read-only", "remount it read-write"),
    errno.ENAMETOOLONG: ("the path is too long for its filesystem", "use a shorter path"),
    errno.EXDEV: ("a rename across two filesystems", "keep both paths on one filesystem"),
    errno.EIO: ("an input/output error (a failing disk or a lost network mount)", "check the disk and its mount"),
    errno.ESTALE: ("a stale network file handle (the share was remounted or lost)", "mount it again"),
    errno.ENOTCONN: ("its filesystem is not connected (a lost FUSE or network mount)", "mount it again"),
    errno.ENODEV: ("its device is gone (a lost mount)", "mount it again"),
}
_GONE = ("its directory does not exist (an unmounted filesystem, or removed during the run)",
         "mount it again, or create the directory")


def _mb(n: int) -> str:
    """Bytes in the unit that suits them: 40 kB, 2.1 MB, 3.5 GB."""
    return f"{n / 1e3:.0f} kB" if n < 1e6 else f"{n / 1e6:.1f} MB" if n < 1e9 else f"{n / 1e9:.1f} GB"


def _existing(path: Path) -> Path | None:
    """`path` or its nearest existing ancestor (None if none is reachable)."""
    for p in (path, *path.parents):
        try:
            if p.exists():
                return p
        except OSError:
            return None
    return None


def environment_problem(e: BaseException, path: str | Path | None = None, what: str = "", need: int | None = None,
                        fix: str = "", kept: str = "") -> EnvironmentProblem | None:
    """The one-line EnvironmentProblem for an OSError the machine caused, or None (a bug, or not an
    OSError). It names the path (the exception's own, else `path`), `what` the command needed there
    and, for a full disk, about how much (`need` bytes) and how much is free; then the errno's fix,
    the command's `fix` (e.g. "give --work on another disk") and what is `kept` for a rerun.
    ENOENT counts only when the file's directory is gone (a lost mount), not a file ours to write."""
    if not isinstance(e, OSError):
        return None
    code = e.errno if e.errno is not None else errno.EACCES if isinstance(e, PermissionError) else None
    at = e.filename if e.filename is not None else path
    if code == errno.ENOENT:
        if at is None or "://" in str(at) or _existing(Path(at).parent) == Path(at).parent:
            return None
        said, remedy = _GONE
    elif code in _ENVIRONMENT:
        said, remedy = _ENVIRONMENT[code]
    else:
        return None
    shown = f"{at} -> {e.filename2}" if e.filename2 is not None else at  # a rename: both paths
    head = f"{shown}: {said}" if at is not None else said.capitalize()
    needed = [what] if what else []
    if code in (errno.ENOSPC, errno.EDQUOT):
        if need:
            needed.append(f"needs about {_mb(need)} more")
        free = _existing(Path(at)) if at is not None and "://" not in str(at) else None
        if free is not None:
            needed.append(f"{_mb(shutil.disk_usage(free).free)} free now")
    parts = [head + (f" ({'; '.join(needed)})" if needed else ""), " or ".join(x for x in (remedy, fix) if x)]
    return EnvironmentProblem("; ".join([*parts, *([kept] if kept else [])]))
