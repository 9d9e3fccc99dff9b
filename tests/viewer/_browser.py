"""Headless Chromium for the viewer's tests: a page at a given URL hash → a screenshot (numpy, uint8 RGB).

Chromium runs with software WebGL (SwiftShader), no network service, an empty profile and no background
traffic. ``chromium()`` is None where no Chromium is installed (``make test`` installs the Debian package).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--hide-scrollbars", "--force-device-scale-factor=1", "--mute-audio")

#: Block every host name and proxy every request into a closed port: a page that asked for anything from the
#: network would fail to get it.
NO_NETWORK = ("--host-resolver-rules=MAP * ~NOTFOUND", "--proxy-server=127.0.0.1:9", "--proxy-bypass-list=<-loopback>")


def chromium() -> str | None:
    for name in (os.environ.get("REFLECTMM_CHROMIUM"), "chromium", "chromium-browser", "google-chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _run(args: list[str], timeout: float) -> subprocess.CompletedProcess:
    exe = chromium()
    if exe is None:
        raise RuntimeError("no Chromium (apt-get install chromium)")
    with tempfile.TemporaryDirectory(prefix="reflectmm-chromium-") as prof:
        return subprocess.run([exe, *FLAGS, f"--user-data-dir={prof}", *args], capture_output=True, text=True,
                              timeout=timeout)


def screenshot(page: Path, hash_: str, size: tuple[int, int], *, offline: bool = True,
               timeout: float = 240) -> np.ndarray:
    """(H, W, 3) uint8 screenshot of ``page`` at ``#hash_`` in a W×H window."""
    from PIL import Image

    w, h = size
    with tempfile.TemporaryDirectory(prefix="reflectmm-shot-") as tmp:
        out = Path(tmp) / "shot.png"
        url = Path(page).absolute().as_uri() + "#" + hash_.lstrip("#")
        r = _run([*(NO_NETWORK if offline else ()), f"--window-size={w},{h}", "--virtual-time-budget=60000",
                  f"--screenshot={out}", url], timeout)
        if not out.exists():
            raise RuntimeError(f"chromium wrote no screenshot (exit {r.returncode}): {r.stderr[-2000:]}")
        return np.asarray(Image.open(out).convert("RGB"))


def dom(page: Path, hash_: str = "", *, offline: bool = True, timeout: float = 240, query: str = "",
        size: tuple[int, int] | None = None) -> str:
    """The page's DOM after load (``--dump-dom``), e.g. to read ``<body data-ready data-error>``."""
    url = (Path(page).absolute().as_uri() + (f"?{query}" if query else "")
           + ("#" + hash_.lstrip("#") if hash_ else ""))
    if size is not None:
        r = _run([*(NO_NETWORK if offline else ()), f"--window-size={size[0]},{size[1]}", "--virtual-time-budget=60000",
                  "--dump-dom", url], timeout)
        return r.stdout
    r = _run([*(NO_NETWORK if offline else ()), "--virtual-time-budget=60000", "--dump-dom", url], timeout)
    return r.stdout


if __name__ == "__main__":  # python tests/viewer/_browser.py PAGE.html 'HASH' WxH OUT.png
    import sys

    from PIL import Image

    page, state, size, out = sys.argv[1:5]
    w, h = (int(x) for x in size.split("x"))
    Image.fromarray(screenshot(Path(page), state, (w, h))).save(out, optimize=True)
