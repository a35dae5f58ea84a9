"""The run lock: one `ga3ce-prep run` per work directory and per output at a time.

Exclusive `flock`s on `<work>/lock` (the cache and finalize's scratch) and on `<out>.lock` beside
the output (so two runs with different work directories cannot both write one store), held for
the whole run. The kernel releases them when the process ends, however it ends (SIGKILL included),
so a killed run never leaves a stale lock and the same command can resume at once. The lock files
stay (removing a lock file races with a run opening it); each records who holds it, for the
refusal message.

A work directory or output on object storage (a URL) has no flock, so its lock has two parts:
- the same flock on a local file named after the URL (`<tmp>/ga3ce-prep-locks/`): runs on this
  machine exclude each other exactly, and a killed run's lock goes with it;
- for the work directory, a lease object `<work>/lock` (host, pid, start, heartbeat) for runs on
  other machines: created with a conditional PUT that fails when it exists, rewritten every
  HEARTBEAT_S seconds, deleted at the end. A lease held by a live process, or by another machine
  within LEASE_S seconds of its last heartbeat, refuses the run; a lease of a dead process of this
  machine, or one without a heartbeat for LEASE_S (its run died), is taken over. A run that finds
  its lease taken over (it stalled past LEASE_S) stops before it writes the store (`check`).
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import socket
import tempfile
import threading
import time
from pathlib import Path

from ..errors import StoreError
from .location import Location, filesystem, is_remote

LEASE_S = 120.0
HEARTBEAT_S = 30.0


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _local_lock_file(location: str, suffix: str) -> Path:
    """The local file whose flock stands for `location + suffix`: itself when local, else a file in
    `<tmp>/ga3ce-prep-locks/` named after the URL."""
    if not is_remote(location):
        return Path(f"{str(location).rstrip('/')}{suffix}")
    name = hashlib.sha256(f"{location}{suffix}".encode()).hexdigest()[:32]
    return Path(tempfile.gettempdir()) / "ga3ce-prep-locks" / f"{name}.lock"


class RunLock:
    """Context manager: `with RunLock(work_dir, out): ...`; StoreError naming the holder if another
    run holds the work directory or the output."""

    def __init__(self, work: Location, out: str):
        self.out = out
        self.lease = f"{str(work).rstrip('/')}/lock" if is_remote(work) else None
        self.paths = (_local_lock_file(str(work), "/lock"), _local_lock_file(str(out), ".lock"))
        self._started = time.strftime("%Y-%m-%d %H:%M:%S")
        where = work if is_remote(work) else Path(work).resolve()
        self.holder = (f"{out} (pid {os.getpid()} on {socket.gethostname()}, work directory {where}, "
                       f"started {self._started})")
        self.fds: list[int] = []
        self.lost: dict | None = None  # the holder that took the lease over, if one did
        self._stop = threading.Event()
        self._beat: threading.Thread | None = None

    def __enter__(self) -> RunLock:
        try:
            for path in self.paths:
                self.fds.append(self._acquire(path))
            if self.lease:
                self._take_lease()
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
        if self._beat is not None:
            self._stop.set()
            self._beat.join()
            self._beat = None
            if self._ours(self._holder()):
                self.fs.rm_file(self.lease)
        while self.fds:
            fd = self.fds.pop()
            os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def check(self) -> None:
        """StoreError if another run took the lease over (this one stalled past LEASE_S)."""
        if self.lost is not None:
            raise StoreError(f"the lock on {self.out} was taken over by pid {self.lost.get('pid')} on "
                             f"{self.lost.get('host')} while this run stalled; nothing was written to the store. "
                             "Let that run finish")

    def _record(self) -> bytes:
        return json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "started": self._started,
                           "heartbeat": time.time()}).encode()

    def _ours(self, held: dict) -> bool:
        return held.get("host") == socket.gethostname() and held.get("pid") == os.getpid()

    def _holder(self) -> dict:
        try:
            held = json.loads(self.fs.cat_file(self.lease))
            return held if isinstance(held, dict) else {}
        except (FileNotFoundError, ValueError):
            return {}

    def _take_lease(self) -> None:
        assert self.lease is not None  # a remote work directory's
        self.fs = filesystem(self.lease, "--work")
        try:
            self.fs.pipe_file(self.lease, self._record(), mode="create")
        except FileExistsError:
            held = self._holder()
            age = time.time() - float(held.get("heartbeat", 0))
            here = held.get("host") == socket.gethostname()
            if (here and _alive(int(held.get("pid", 0)))) or (not here and age < LEASE_S):
                raise StoreError(
                    f"another ga3ce-prep run is writing {self.out} (pid {held.get('pid')} on {held.get('host')}, "
                    f"started {held.get('started')}, last heard of {age:.0f} s ago); wait for it to finish, or stop it "
                    f"and rerun this command to resume (lease: {self.lease}; a lease without a heartbeat for "
                    f"{LEASE_S:.0f} s is taken over)") from None
            self.fs.pipe_file(self.lease, self._record())  # its run is gone
        self._beat = threading.Thread(target=self._heartbeat, name="ga3ce-lease", daemon=True)
        self._beat.start()

    def _heartbeat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            try:
                held = self._holder()
                if held and not self._ours(held):
                    self.lost = held
                    return
                self.fs.pipe_file(self.lease, self._record())
            except Exception:  # a missed beat; the next one retries
                continue
