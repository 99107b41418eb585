"""Open a report in a real headless browser (Chromium): the rendered DOM, the console
errors and a screenshot. Used by the tests and by ``prism3d demo --screenshot``.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from prism3d.errors import InputError

__all__ = ["BrowserCheck", "find_chromium", "check_page"]

_CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome executable (``PRISM3D_CHROMIUM`` overrides), or None."""
    env = os.environ.get("PRISM3D_CHROMIUM")
    if env:
        return env if Path(env).exists() else None
    for name in _CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


@dataclass
class BrowserCheck:
    """What the browser saw."""

    dom: str
    console_errors: list[str]
    screenshot: Path | None

    def attribute(self, name: str) -> str | None:
        m = re.search(rf"<body[^>]*\b{re.escape(name)}=\"([^\"]*)\"", self.dom)
        return m.group(1) if m else None


_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-default-apps", "--disable-extensions", "--hide-scrollbars", "--mute-audio",
]


def check_page(html_path: str | Path, *, screenshot: str | Path | None = None, width: int = 1200,
               height: int = 4000, budget_ms: int = 8000, timeout_s: float = 120.0) -> BrowserCheck:
    """Load ``html_path`` in headless Chromium; return the DOM after scripts ran, the
    console errors (uncaught exceptions, console.error, failed loads) and optionally a
    full-page screenshot.

    Raises
    ------
    InputError
        No browser found, or the page is missing.
    """
    exe = find_chromium()
    if exe is None:
        raise InputError("no Chromium found: install it (Debian: apt-get install chromium) or set PRISM3D_CHROMIUM")
    page = Path(html_path).resolve()
    if not page.is_file():
        raise InputError(f"{page}: page not found")
    url = page.as_uri()
    with tempfile.TemporaryDirectory(prefix="prism3d-chromium-") as profile:
        base = [exe, *_FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
                f"--virtual-time-budget={budget_ms}", "--enable-logging=stderr", "--v=0"]
        r = subprocess.run([*base, "--dump-dom", url], capture_output=True, text=True, timeout=timeout_s)
        errors = [line for line in r.stderr.splitlines()
                  if "CONSOLE" in line and ("Uncaught" in line or "Error" in line or "error" in line)]
        errors += [line for line in r.stderr.splitlines() if "Failed to load resource" in line]
        shot = None
        if screenshot is not None:
            shot = Path(screenshot).resolve()
            shot.parent.mkdir(parents=True, exist_ok=True)
            subprocess.run([*base, f"--screenshot={shot}", url], capture_output=True, text=True,
                           timeout=timeout_s)
            if not shot.exists():
                shot = None
    return BrowserCheck(r.stdout, errors, shot)
