"""Render a run's report.html in headless Chromium and save a PNG screenshot.

Checks that the self-contained report renders without network access (Chromium is
started with background networking off). Needs Debian's `chromium` package.

    .venv/bin/python scripts/screenshot_report.py OUT [--png report.png]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a recon3d output folder")
    parser.add_argument("--png", type=Path, default=None, help="screenshot path (default OUT/report.png)")
    args = parser.parse_args()
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        print("chromium not found: apt-get install chromium", file=sys.stderr)
        return 1
    page = (args.out_dir / "report.html").resolve()
    png = (args.png or args.out_dir / "report.png").resolve()
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run(
            [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={profile}", "--window-size=1200,2400", f"--screenshot={png}", page.as_uri()],
            check=True, capture_output=True, timeout=120,
        )
    print(f"wrote {png} ({png.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
