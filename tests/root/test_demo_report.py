"""The demo end to end (fast mode), and its report opened in a real headless browser."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from prism3d.browser import check_page, find_chromium


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    r = subprocess.run([sys.executable, "-m", "prism3d.cli", "demo", str(out), "--fast"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return out


def test_demo_artefacts(demo_out):
    html = (demo_out / "report.html").read_text()
    assert "FAILED" not in html
    for section in ("Installation check", "Virtual prism rig", "Calibration", "Table I", "360-degree model",
                    "Camouflage removal", "ATR features", "Whole-scene ATR", "UAV mode"):
        assert section in html, section
    for rel in re.findall(r"href='([^'#]+)'", html):
        assert (demo_out / rel).exists(), rel  # every linked artefact exists
    assert "http://" not in html and "https://" not in html  # offline: no CDN


@pytest.mark.skipif(find_chromium() is None, reason="Chromium not installed (make setup installs it)")
def test_report_renders_in_headless_chromium(demo_out):
    shot = demo_out / "report_screenshot.png"
    check = check_page(demo_out / "report.html", screenshot=shot, height=3000)
    assert check.console_errors == []
    n_img = int(check.attribute("data-images"))
    assert n_img >= 8 and check.attribute("data-images-ok") == str(n_img)  # every figure decoded
    assert "<canvas" in check.dom and 'data-ready="1"' in check.dom  # the 3D view drew
    m = re.search(r'data-points="(\d+)"', check.dom)
    assert m and int(m.group(1)) > 1000
    assert shot.exists() and shot.stat().st_size > 10_000
