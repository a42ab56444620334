"""Open a run in `recon3d view` in headless Chromium and save a PNG screenshot.

Software WebGL (SwiftShader), no network: the page and three.js come from the local
server. Needs Debian's `chromium` package and the `playwright` Python package (it
drives /usr/bin/chromium; no browser download).

    .venv/bin/python scripts/screenshot_viewer.py OUT [--png viewer.png] [--mode lod|quality|photo] [--select ID]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import threading
from pathlib import Path

#: Chromium flags for WebGL without a GPU.
WEBGL_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="a recon3d output folder")
    parser.add_argument("--png", type=Path, default=None, help="screenshot path (default OUT/viewer.png)")
    parser.add_argument("--mode", choices=["lod", "quality", "photo"], default="lod",
                        help="colouring (photo: the model textured from the images, stereo runs)")
    parser.add_argument("--select", metavar="ID", help="click this building first (default: the first one)")
    parser.add_argument("--size", default="1400x900", help="window size WxH")
    args = parser.parse_args()
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        print("chromium not found: apt-get install chromium", file=sys.stderr)
        return 1
    from playwright.sync_api import sync_playwright

    from recon3d.viewer import start_server

    server = start_server(args.out_dir)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    width, height = map(int, args.size.split("x"))
    png = args.png or args.out_dir / "viewer.png"
    try:
        with sync_playwright() as p:
            chromium = p.chromium.launch(executable_path=browser, args=WEBGL_FLAGS)
            page = chromium.new_page(viewport={"width": width, "height": height})
            page.goto(server.url)
            page.wait_for_function("window.recon3dViewer && (window.recon3dViewer.ready || window.recon3dViewer.error)")
            error = page.evaluate("window.recon3dViewer.error")
            if error:
                print(f"the viewer failed: {error}", file=sys.stderr)
                return 1
            page.evaluate(f"window.recon3dViewer.setMode({args.mode!r})")
            ids = page.evaluate("window.recon3dViewer.ids")
            if ids:
                point = page.evaluate(f"window.recon3dViewer.project({(args.select or ids[0])!r})")
                page.mouse.click(point["x"], point["y"])
            page.screenshot(path=str(png))
            chromium.close()
    finally:
        server.shutdown()
        server.server_close()
    print(f"wrote {png} ({len(ids)} buildings)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
