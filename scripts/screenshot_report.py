"""Render a run's report.html in headless Chromium and save a full-page PNG screenshot.

Checks that the self-contained report renders without network access (any request
beyond the file and its data URIs is reported) and that its images decode. Needs
Debian's `chromium` package and the `playwright` Python package (the dev extra),
which drives that chromium (no browser download).

    .venv/bin/python scripts/screenshot_report.py OUT [--png report.png] [--width 1200]
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a recon3d output folder")
    parser.add_argument("--png", type=Path, default=None, help="screenshot path (default OUT/report.png)")
    parser.add_argument("--width", type=int, default=1200, help="viewport width (px)")
    args = parser.parse_args()
    browser_path = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser_path is None:
        print("chromium not found: apt-get install chromium", file=sys.stderr)
        return 1
    from playwright.sync_api import sync_playwright

    page_path = (args.out_dir / "report.html").resolve()
    if not page_path.is_file():
        print(f"{page_path}: no report.html (recon3d report {args.out_dir} writes it)", file=sys.stderr)
        return 1
    png = (args.png or args.out_dir / "report.png").resolve()
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=browser_path, args=["--no-sandbox", "--disable-gpu"])
        page = browser.new_page(viewport={"width": args.width, "height": 900})
        outside = []
        page.on("request", lambda r: outside.append(r.url) if not r.url.startswith(("file:", "data:")) else None)
        page.goto(page_path.as_uri(), wait_until="load")
        page.screenshot(path=str(png), full_page=True)
        images = page.evaluate("Array.from(document.images).map(i => [i.alt, i.naturalWidth, i.naturalHeight])")
        rows = page.locator("table.buildings tbody tr").count()
        browser.close()
    for alt, w, h in images:
        print(f"image {alt}: {w} x {h} px")
    print(f"{rows} building rows; wrote {png} ({png.stat().st_size} bytes)")
    if outside:
        print(f"requests outside the file: {outside}", file=sys.stderr)
    broken = [alt for alt, w, h in images if not w or not h]
    return 1 if outside or broken else 0


if __name__ == "__main__":
    sys.exit(main())
