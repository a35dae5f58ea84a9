"""The run lock: one `ga3ce-prep run` per work directory and per output at a time.

Exclusive `flock`s on `<work>/lock` (the cache and finalize's scratch) and on `<out>.lock` beside
the output (so two runs with different work directories cannot both write one store), held for
the whole run. The kernel releases them when the process ends, however it ends (SIGKILL
included), so a killed run never leaves a stale lock and the same command can resume at once. The
lock files stay (removing a lock file races with a run opening it); each records who holds it,
for the refusal message.
"""
from __future__ import annotations

import fcntl
import os
import socket
import time
from pathlib import Path

from ..errors import StoreError


class RunLock:
    """Context manager: `with RunLock(work_dir, out): ...`; StoreError naming the holder if another
    run holds the work directory or the output."""

    def __init__(self, work: Path, out: str):
        self.paths = (Path(work) / "lock", Path(f"{out}.lock"))
        self.holder = (f"{out} (pid {os.getpid()} on {socket.gethostname()}, work directory {Path(work).resolve()}, "
                       f"started {time.strftime('%Y-%m-%d %H:%M:%S')})")
        self.fds: list[int] = []

    def __enter__(self) -> "RunLock":
        try:
            for path in self.paths:
                self.fds.append(self._acquire(path))
        except BaseException:
            self.__exit__()
            raise
        return self

    def _acquire(self, path: Path) -> int:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "an unknown process"
            os.close(fd)
            raise StoreError(f"another ga3ce-prep run is writing {holder} and holds {path}; wait for it to finish, "
                             "or stop it and rerun this command to resume") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, self.holder.encode(), 0)
        return fd

    def __exit__(self, *exc) -> None:
        while self.fds:
            fd = self.fds.pop()
            os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
