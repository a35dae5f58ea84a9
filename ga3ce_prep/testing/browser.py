"""A page in headless chromium, driven over the DevTools protocol (its websocket, through tornado's
client, which dask's distributed already installs): load it, wait for a condition, read values, take a
screenshot. WebGL runs on SwiftShader (no GPU); every host name but the loopback's resolves to
nothing, so the page reaches no other machine (a page that would fetch fonts or telemetry gets an
error instead). For the web viewer's test (tests/test_view.py) and its screenshot in the manual
(benchmarks/bench_view.py)."""
from __future__ import annotations

import asyncio
import base64
import json
import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

FLAGS = ("--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
         "--disable-default-apps", "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.0.0.1")


@dataclass
class Page:
    """What the page showed: `values` (name -> the JavaScript expression's value when the condition
    held or the time ran out), `ready` (the condition held), the console's errors and exceptions, and
    the screenshot's PNG bytes (b"" when none was asked)."""

    values: dict[str, Any] = field(default_factory=dict)
    ready: bool = False
    errors: list[str] = field(default_factory=list)
    png: bytes = b""


def chromium() -> str:
    """The chromium executable; RuntimeError saying how to install it."""
    exe = shutil.which("chromium")
    if exe is None:
        raise RuntimeError("chromium is not installed: run `make setup` (scripts/setup.sh installs Debian's chromium)")
    return exe


def render(url: str, ready: Callable[[dict[str, Any]], bool], values: dict[str, str], timeout: float = 90.0,
           size: tuple[int, int] = (1280, 800), screenshot: bool = False, poll: float = 2.0,
           settle: float = 0.0) -> Page:
    """Open `url` in a page of `size` (W, H) px; every `poll` seconds evaluate `values` (name -> JavaScript
    expression) until ready(those values) holds or `timeout` seconds pass; then, if asked, take a screenshot
    `settle` seconds later (the page drawing what arrived last)."""
    profile = tempfile.mkdtemp(prefix="ga3ce-chromium-")
    proc = subprocess.Popen([chromium(), *FLAGS, f"--user-data-dir={profile}", "--remote-debugging-port=0",
                             f"--window-size={size[0]},{size[1]}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        return asyncio.run(_drive(_devtools_url(Path(profile), proc), url, ready, values, timeout, screenshot, poll,
                              size, settle))
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(profile, ignore_errors=True)


def _devtools_url(profile: Path, proc: subprocess.Popen, timeout: float = 30.0) -> str:
    """The websocket of chromium's first page, once chromium has written its DevTools port."""
    import urllib.request

    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        port_file = profile / "DevToolsActivePort"
        if port_file.is_file() and port_file.read_text().strip():
            port = port_file.read_text().split()[0]
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json") as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            if pages:
                return pages[0]["webSocketDebuggerUrl"]
        time.sleep(0.1)
    raise RuntimeError(f"chromium did not start (exit code {proc.poll()})")


async def _drive(ws_url: str, url: str, ready: Callable[[dict[str, Any]], bool], values: dict[str, str],
                 timeout: float, screenshot: bool, poll: float, size: tuple[int, int], settle: float) -> Page:
    from tornado.websocket import websocket_connect

    ws = await websocket_connect(ws_url, max_message_size=256 << 20)
    page = Page()
    n = 0

    async def call(method: str, **params: Any) -> dict[str, Any]:
        nonlocal n
        n += 1
        await ws.write_message(json.dumps({"id": n, "method": method, "params": params}))
        while True:
            msg = await ws.read_message()
            if msg is None:
                raise RuntimeError("chromium closed the DevTools connection")
            m = json.loads(msg)
            if m.get("id") == n:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})
            p = m.get("params", {})
            if m.get("method") == "Runtime.exceptionThrown":
                page.errors.append(p["exceptionDetails"].get("text", "") + " " + json.dumps(
                    p["exceptionDetails"].get("exception", {}).get("description", ""))[:300])
            elif m.get("method") == "Runtime.consoleAPICalled" and p.get("type") == "error":
                page.errors.append(" ".join(str(a.get("value", a.get("description", ""))) for a in p["args"])[:300])

    await call("Runtime.enable")
    await call("Page.enable")
    await call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1, mobile=False)
    await call("Page.navigate", url=url)
    end = time.monotonic() + timeout
    while True:
        for name, expression in values.items():
            r = await call("Runtime.evaluate", expression=expression, returnByValue=True)
            page.values[name] = r.get("result", {}).get("value")
        page.ready = bool(ready(page.values))
        if page.ready or time.monotonic() > end:
            break
        await asyncio.sleep(poll)
    if screenshot:
        await asyncio.sleep(settle)
        page.png = base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])
    ws.close()
    return page


# Rerun's web viewer: its state, and the recording it holds as RRD bytes in base64 (WebHandle.save_recording)
VIEWER_STATE = {
    "started": "!!window._handle", "panicked": "window._handle ? window._handle.has_panicked() : null",
    "message": "document.getElementById('center_text').innerText",
    "rrd": ("(() => { try { const b = window._handle.save_recording(); let s = ''; for (let i = 0; i < b.length; "
            "i += 0x8000) s += String.fromCharCode.apply(null, b.subarray(i, i + 0x8000)); return btoa(s); } "
            "catch (e) { return ''; } })()")}


def rerun_web_viewer(url: str, frames: int, held: Path, timeout: float = 120.0, settle: float = 0.0) -> Page:
    """Rerun's web viewer at `url` (`ga3ce-prep view --serve`) until the recording it holds has `frames`
    frames (rows of frames/id), then a screenshot `settle` seconds later; the held recording is left in
    `held` (.rrd) for reading back (testing/recordings.py)."""
    from .recordings import read_recording

    def arrived(v: dict[str, Any]) -> bool:
        if not (v.get("started") and v.get("rrd")):
            return False
        held.write_bytes(base64.b64decode(v["rrd"]))
        return len(read_recording(held, blobs=False).at("/frames/id", "row")) >= frames

    return render(url, arrived, VIEWER_STATE, timeout=timeout, screenshot=True, settle=settle)
