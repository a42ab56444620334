"""The 3D Tiles of the shared runs in CesiumJS (npm ``cesium`` in tools/), headless Chromium.

A throwaway ``http.server`` thread serves the test page (tools/cesium/), CesiumJS's
``Build/Cesium`` and one tileset folder, and records every path asked for. The page
(no Cesium ion, no imagery, no terrain) loads the tileset with
``Cesium3DTileset.fromUrl``, flies to it and waits for ``allTilesLoaded``. Checked: no
``tileFailed``, page or render error, no request off localhost; every content of tileset.json requested from the
server and loaded (``tileLoad``); one feature per building with a solid, its
``getProperty("id")`` that building's id; and a pick at the screen centre over one
building (straight down on a point inside each footprint) returns that building. On the run's own tileset (one content for a village)
and on the same buildings cut into tiles of at most 2 (a quadtree Cesium has to refine).
"""

from __future__ import annotations

import functools
import http.server
import os
import shutil
import threading
import urllib.parse
from pathlib import Path

import numpy as np
import pytest
from conftest import chromium
from test_viewer import WEBGL_FLAGS
from tiles3d_checks import check_tileset

from recon3d.io.tiles3d import to_ecef, write_3dtiles

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "tools" / "cesium"
CESIUM_BUILD = ROOT / "tools" / "node_modules" / "cesium" / "Build" / "Cesium"


class _Handler(http.server.SimpleHTTPRequestHandler):
    """``/cesium/...`` from CesiumJS's build, ``/tiles/...`` from the tileset folder, the
    rest from the page folder; every path asked for is appended to ``requested``."""

    def __init__(self, *args, tiles: Path, requested: list[str], **kwargs):
        self.tiles, self.requested = tiles, requested
        super().__init__(*args, directory=str(PAGE), **kwargs)

    def translate_path(self, path: str) -> str:
        self.requested.append(path.split("?", 1)[0])
        for prefix, folder in (("/cesium/", CESIUM_BUILD), ("/tiles/", self.tiles)):
            if path.startswith(prefix):
                return super().translate_path("/" + path[len(prefix):]).replace(str(PAGE), str(folder), 1)
        return super().translate_path(path)

    def send_error(self, code, message=None, explain=None) -> None:
        self.requested.append(f"{code} {self.path}")
        super().send_error(code, message, explain)

    def log_message(self, *args) -> None:
        pass


def _serve(tiles: Path) -> tuple[http.server.ThreadingHTTPServer, list[str]]:
    requested: list[str] = []
    handler = functools.partial(_Handler, tiles=tiles, requested=requested)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, requested


def load_in_cesium(tiles: Path, pick: dict[str, np.ndarray]) -> tuple[dict, list[str], dict[str, str | None]]:
    """What the page saw loading the tileset in ``tiles``, the paths the server was asked
    for, and the id picked at the screen centre over each EPSG:4978 point of ``pick``."""
    from playwright.sync_api import sync_playwright

    if not (CESIUM_BUILD / "Cesium.js").is_file():
        message = "CesiumJS is not installed: run `npm ci --prefix tools` (README, Install)"
        if shutil.which("npm") is None and os.environ.get("CI") != "true":
            pytest.skip(f"npm is not installed: {message}")
        pytest.fail(message)
    browser = chromium()
    server, requested = _serve(tiles)
    console: list[str] = []
    try:
        with sync_playwright() as p:
            chrome = p.chromium.launch(executable_path=browser, args=WEBGL_FLAGS)
            try:
                page = chrome.new_page(viewport={"width": 800, "height": 600})
                page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
                page.on("pageerror", lambda e: console.append(str(e)))
                port = server.server_address[1]
                local = f"http://127.0.0.1:{port}/"
                page.route(lambda url: not url.startswith(local),  # no Cesium ion, nothing off this machine
                           lambda route: (console.append(f"outside request: {route.request.url}"), route.abort()))
                page.goto(f"http://127.0.0.1:{port}/index.html?tileset=/tiles/tileset.json&timeout=120000")
                page.wait_for_function("window.tilesetCheck && window.tilesetCheck.done", timeout=180_000)
                seen = page.evaluate("({...window.tilesetCheck, pickAt: undefined})")
                picked = {bid: page.evaluate("p => window.tilesetCheck.pickAt(...p)", [float(v) for v in xyz])
                          for bid, xyz in pick.items()} if seen["error"] is None else {}
            finally:
                chrome.close()
    finally:
        server.shutdown()
        server.server_close()
    seen["errors"] += console
    return seen, requested, picked


def _roof_point(state, building) -> np.ndarray:
    """(3,) EPSG:4978 point over ``building``: inside its footprint (world coordinates), at
    the top of its solids."""
    inside = building.footprint.representative_point()
    top = max(state.city.frame.to_world(s.vertices)[:, 2].max() for s in building.solids.values())
    return to_ecef(np.array([[inside.x, inside.y, top]]), state.city.crs)[0]


@pytest.mark.slow
@pytest.mark.parametrize("fixture", ["delft_run", "ign_run"])
@pytest.mark.parametrize("max_buildings", [None, 2])
def test_3dtiles_of_a_run_load_in_cesium(fixture, max_buildings, request, record_property, tmp_path):
    state = request.getfixturevalue(fixture)
    folder = state.out_dir / "buildings_3dtiles"
    if max_buildings is not None:
        folder = tmp_path / "split"
        write_3dtiles(state.city, folder, max_buildings=max_buildings)
    uris = sorted(check_tileset(folder)["contents"])
    solid = {b.id: b for b in state.city if b.solids}
    seen, requested, picked = load_in_cesium(folder, {bid: _roof_point(state, b) for bid, b in solid.items()})
    record_property("cesium_load_seconds", seen["seconds"])

    assert seen["error"] is None and seen["errors"] == [] and seen["failed"] == [], seen
    assert sorted(p[len("/tiles/"):] for p in requested if p.endswith(".glb")) == uris
    assert sorted(urllib.parse.urlsplit(u).path for u in seen["loaded"]) == [f"/tiles/{u}" for u in uris]
    assert seen["features"] == len(solid)
    assert sorted(seen["ids"]) == sorted(solid)
    assert picked == {bid: bid for bid in solid}  # looking straight down on each roof
