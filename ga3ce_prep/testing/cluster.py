"""Servers the scale-out tests and benchmarks start on loopback and stop again: a dask cluster made
with the standard CLIs (`dask scheduler`, `dask worker`) and moto's S3 server."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path


def _stop(p: subprocess.Popen, grace: float = 20.0) -> None:
    """SIGTERM the process group we started (a nanny and its worker), then SIGKILL it after `grace`."""
    if p.poll() is not None:
        return
    for sig, wait in ((signal.SIGTERM, grace), (signal.SIGKILL, 10.0)):
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            return
        try:
            p.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _wait_for(check, what: str, procs: list[subprocess.Popen], timeout: float) -> None:
    t = time.monotonic()
    while not check():
        dead = [p for p in procs if p.poll() is not None]
        if dead:
            raise RuntimeError(f"{what}: {dead[0].args!r} exited with {dead[0].returncode}")
        if time.monotonic() - t > timeout:
            raise TimeoutError(f"{what}: not ready after {timeout:.0f} s")
        time.sleep(0.2)


@contextmanager
def dask_cluster(tmp: Path, n_workers: int = 2, worker_env: dict[str, str] | None = None,
                 timeout: float = 120.0) -> Iterator[str]:
    """A scheduler and `n_workers` single-threaded workers (each with its nanny, which restarts a
    killed worker) on 127.0.0.1; yields the scheduler's address. worker_env: extra environment of
    the workers. Logs go to tmp/scheduler.log and tmp/worker-<i>.log."""
    tmp.mkdir(parents=True, exist_ok=True)
    info = tmp / "scheduler.json"
    info.unlink(missing_ok=True)
    dask = [sys.executable, "-m", "dask"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with ExitStack() as stack:
        def start(args: list[str], log: str, extra: dict[str, str] | None = None) -> subprocess.Popen:
            p = subprocess.Popen([*dask, *args], env={**env, **(extra or {})}, start_new_session=True,
                                 stdout=open(tmp / log, "w"), stderr=subprocess.STDOUT)
            stack.callback(_stop, p)
            return p

        sched = start(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                       "--scheduler-file", str(info), "--idle-timeout", "900"], "scheduler.log")
        _wait_for(info.is_file, "dask scheduler", [sched], timeout)
        address = json.loads(info.read_text())["address"]
        procs = [sched] + [start(["worker", address, "--nthreads", "1", "--no-dashboard", "--name", f"w{i}",
                                  "--death-timeout", "120"], f"worker-{i}.log", worker_env)
                           for i in range(n_workers)]

        def ready() -> bool:
            from distributed import Client

            with Client(address, timeout=10) as c:
                return len(c.scheduler_info(n_workers=-1)["workers"]) >= n_workers

        _wait_for(ready, f"{n_workers} dask workers", procs, timeout)
        yield address


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def moto_s3(tmp: Path, timeout: float = 60.0) -> Iterator[dict[str, str]]:
    """moto's S3 server on 127.0.0.1; yields the environment that points s3fs (and every AWS
    client) at it with dummy credentials. Its log goes to tmp/moto.log."""
    with moto_server(tmp, timeout) as (env, _):
        yield env


@contextmanager
def moto_server(tmp: Path, timeout: float = 60.0) -> Iterator[tuple[dict[str, str], subprocess.Popen]]:
    """`moto_s3`, with the server's process too (to freeze it: `frozen`)."""
    tmp.mkdir(parents=True, exist_ok=True)
    port = free_port()
    p = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
                         start_new_session=True, stdout=open(tmp / "moto.log", "w"), stderr=subprocess.STDOUT)
    try:
        def up() -> bool:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                return True
            except OSError:
                return False

        _wait_for(up, "moto server", [p], timeout)
        yield {"AWS_ENDPOINT_URL_S3": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "testing",
               "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}, p
    finally:
        if p.poll() is None:
            os.kill(p.pid, signal.SIGCONT)  # in case it is frozen
        _stop(p)


def frozen(p: subprocess.Popen, after: float, seconds: float) -> threading.Thread:
    """Freeze the process `p` (SIGSTOP: its sockets accept and answer nothing, as a hung endpoint)
    `after` seconds from now for `seconds`, in a thread; join it to know the freeze is over."""
    def freeze() -> None:
        time.sleep(after)
        os.kill(p.pid, signal.SIGSTOP)
        try:
            time.sleep(seconds)
        finally:
            os.kill(p.pid, signal.SIGCONT)

    t = threading.Thread(target=freeze, daemon=True)
    t.start()
    return t
