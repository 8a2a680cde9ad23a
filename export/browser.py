"""Headless Chromium for the viewer: screenshots and frame-rate runs (software WebGL, SwiftShader)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

from damcap.common.errors import DamcapError

CHROMIUM_FLAGS = [
    "--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
    "--disable-quic", "--hide-scrollbars", "--force-device-scale-factor=1",
]


def chromium_path() -> str | None:
    """The Chromium executable, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def _run(args: list[str], timeout_s: float) -> subprocess.CompletedProcess:
    exe = chromium_path()
    if exe is None:
        raise DamcapError("chromium not found; install Debian's 'chromium' package (make test does)")
    with tempfile.TemporaryDirectory(prefix="damcap-chromium-") as profile:
        p = subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args], capture_output=True, text=True, timeout=timeout_s)
    if p.returncode != 0:
        raise DamcapError(f"chromium failed (exit {p.returncode}): {p.stderr.strip().splitlines()[-1:]}")
    return p


def three_js_dir() -> Path | None:
    """Debian's three.js (package ``libjs-three``: ``three.min.js`` and ``examples/js``), or None."""
    p = Path("/usr/share/javascript/three")
    return p if (p / "three.min.js").is_file() else None


def screenshot(page: str | os.PathLike, png: str | os.PathLike, size: int, fragment: str = "", timeout_s: float = 120,
               virtual_time_ms: int = 0) -> None:
    """Load ``page`` (a local HTML file) at size x size and save a PNG screenshot (``virtual_time_ms``:
    let the page's timers and promises run this long first, for pages that draw asynchronously)."""
    url = Path(page).resolve().as_uri() + (f"#{fragment}" if fragment else "")
    wait = [f"--virtual-time-budget={virtual_time_ms}"] if virtual_time_ms else []
    _run([f"--window-size={size},{size}", *wait, f"--screenshot={Path(png).resolve()}", url], timeout_s)
    if not Path(png).is_file():
        raise DamcapError(f"chromium wrote no screenshot for {page}")


def frame_rate(page: str | os.PathLike, size: int, frames: int = 30, timeout_s: float = 300) -> float:
    """Frames per second the page renders (its ``bench`` mode: finished frames, synchronously)."""
    url = Path(page).resolve().as_uri() + f"#bench={frames}&caption=0"
    p = _run([f"--window-size={size},{size}", "--dump-dom", url], timeout_s)
    m = re.search(r"<title>fps=([0-9.]+)</title>", p.stdout)
    if not m:
        raise DamcapError(f"the viewer reported no frame rate (WebGL 2 unavailable?): {p.stdout[-300:]}")
    return float(m.group(1))


def page_title(page: str | os.PathLike, size: int, virtual_time_ms: int = 5000, timeout_s: float = 120) -> str:
    """The page's ``<title>`` after it ran ``virtual_time_ms`` of virtual time (how a test page reports)."""
    url = Path(page).resolve().as_uri()
    p = _run([f"--window-size={size},{size}", f"--virtual-time-budget={virtual_time_ms}", "--dump-dom", url], timeout_s)
    m = re.search(r"<title>(.*?)</title>", p.stdout, re.S)
    return m.group(1) if m else ""
