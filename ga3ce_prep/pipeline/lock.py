"""The run lock: one `ga3ce-prep run` per output at a time.

An exclusive `flock` on `<work>/lock`, held for the whole run. The kernel releases it when the
process ends, however it ends (SIGKILL included), so a killed run never leaves a stale lock and the
same command can resume at once. The file records who holds it, for the refusal message.
"""
from __future__ import annotations

import fcntl
import os
import socket
import time
from pathlib import Path

from ..errors import StoreError


class RunLock:
    """Context manager: `with RunLock(work_dir, out): ...`; StoreError if another run holds it."""

    def __init__(self, work: Path, out: str):
        self.path = Path(work) / "lock"
        self.out = out
        self.fd: int | None = None

    def __enter__(self) -> "RunLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 512, 0).decode(errors="replace").strip() or "unknown process"
            os.close(fd)
            raise StoreError(f"another ga3ce-prep run is writing {self.out} ({holder}); wait for it to finish, "
                             f"or stop it and rerun this command to resume (lock: {self.path})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}, started {time.strftime('%Y-%m-%d %H:%M:%S')}".encode(), 0)
        self.fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            os.ftruncate(self.fd, 0)
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None
