"""Render pmcal's HTML reports with headless Chromium and save full-page screenshots as PNG.

Usage (after ``pmcal demo``, ``pmcal diagnose ... --report diag``, ``pmcal --machine planar_2dof demo``)::

    python tools/screenshot_reports.py pmcal-demo/report.html:docs/report_demo.png \
        diag/index.html:docs/report_diagnose.png pmcal-demo-planar/report.html:docs/report_planar.png

Needs a ``chromium`` binary (Debian: ``apt-get install chromium``). The page height is measured first
(``--dump-dom`` of a page that prints its scroll height), so the screenshot holds the whole report.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars"]
WIDTH = 1400


def chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    sys.exit("no chromium on PATH (apt-get install chromium)")


def page_height(browser: str, html: Path) -> int:
    """Scroll height of the rendered page, px (at WIDTH)."""
    probe = html.parent / f".height-probe-{html.stem}.html"
    probe.write_text(html.read_text(encoding="utf-8").replace(
        "</body>", "<script>document.title='H'+document.documentElement.scrollHeight;</script></body>"),
        encoding="utf-8")
    try:
        dom = subprocess.run([browser, *FLAGS, f"--window-size={WIDTH},800", "--virtual-time-budget=5000",
                              "--dump-dom", probe.resolve().as_uri()], capture_output=True, text=True,
                             timeout=120).stdout
    finally:
        probe.unlink()
    start = dom.find("<title>H")
    return int(dom[start + 8:dom.find("<", start + 8)]) if start >= 0 else 6000


def screenshot(html: Path, png: Path) -> None:
    browser = chromium()
    height = min(page_height(browser, html) + 40, 16000)
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run([browser, *FLAGS, f"--user-data-dir={profile}", f"--window-size={WIDTH},{height}",
                        f"--screenshot={png.resolve()}", html.resolve().as_uri()], check=True,
                       capture_output=True, timeout=180)
    shrink(png)
    print(f"{html} -> {png} ({WIDTH} x {height} px, {png.stat().st_size // 1024} KiB)")


def shrink(png: Path, max_error: int = 24) -> None:
    """Store the screenshot with a 256-colour palette (a third of the size) if no pixel's colour moves by
    more than ``max_error`` (of 255) in any channel; else keep it in full colour."""
    try:
        import numpy as np
        from PIL import Image          # Pillow comes with matplotlib
    except ImportError:
        return
    with Image.open(png) as im:
        rgb = im.convert("RGB")
    ref = np.asarray(rgb, dtype=np.int16)
    for method in (Image.Quantize.MAXCOVERAGE, Image.Quantize.FASTOCTREE):
        small = rgb.quantize(colors=256, method=method, dither=Image.Dither.NONE)
        if np.abs(np.asarray(small.convert("RGB"), dtype=np.int16) - ref).max() <= max_error:
            small.save(png, optimize=True)
            return
    rgb.save(png, optimize=True)


if __name__ == "__main__":
    for spec in sys.argv[1:]:
        src, dst = spec.split(":", 1)
        screenshot(Path(src), Path(dst))
