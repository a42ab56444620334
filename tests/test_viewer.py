"""`recon3d view OUT`: the files it serves, the server, and the page in headless Chromium.

The page test loads the Delft run in Debian's chromium (software WebGL, SwiftShader)
through the playwright package, and checks what a person would: the scene is drawn,
every building of buildings.glb is loaded, and a click on a building shows its id.
"""

from __future__ import annotations

import json
import os
import selectors
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from recon3d.cli import cli
from recon3d.io.geotiff import read_raster
from recon3d.viewer import site_files, start_server

ROOT = Path(__file__).resolve().parents[1]
STATIC = ROOT / "recon3d" / "viewer" / "static"

#: Chromium flags for WebGL without a GPU (as scripts/screenshot_viewer.py).
WEBGL_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]

#: The page's background, #dfe5ea (viewer.js).
BACKGROUND = (0xDF, 0xE5, 0xEA)


def _glb_document(path: Path) -> dict:
    data = path.read_bytes()
    length, _ = struct.unpack_from("<II", data, 12)
    return json.loads(data[20:20 + length])


def _building_extras(out_dir: Path) -> dict[str, dict]:
    """Building id -> node extras of the run's GLB."""
    return {n["extras"]["id"]: n["extras"] for n in _glb_document(out_dir / "buildings.glb")["nodes"]}


def _missing_tool(message: str) -> None:
    """Chromium or playwright absent: a failure in CI, a skip elsewhere (as missing shared data)."""
    if os.environ.get("CI") == "true":
        pytest.fail(message)
    pytest.skip(message)


def _chromium() -> str:
    browser = shutil.which("chromium")
    if browser is None:
        _missing_tool("chromium is not installed (apt-get install chromium): the viewer page cannot be checked")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        _missing_tool("the playwright package is not installed (pip install -e '.[dev]')")
    return browser


@pytest.fixture
def served(delft_run):
    """The Delft run's viewer, served from a thread of this process."""
    server = start_server(delft_run.out_dir)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


def test_refuses_a_folder_that_is_not_a_finished_run(tmp_path):
    runner = CliRunner()
    result = runner.invoke(cli, ["view", str(tmp_path), "--no-browser"])
    assert result.exit_code == 1
    assert "buildings.glb and run.json missing" in result.output, result.output
    (tmp_path / "run.json").write_text("{}", encoding="utf-8")
    result = runner.invoke(cli, ["view", str(tmp_path), "--no-browser"])
    assert result.exit_code == 1
    assert f"{tmp_path}: not a finished recon3d run: buildings.glb missing" in result.output, result.output
    result = runner.invoke(cli, ["view", str(tmp_path / "nowhere"), "--no-browser"])
    assert result.exit_code == 1 and "no such folder" in result.output, result.output
    result = runner.invoke(cli, ["view", str(tmp_path / "run.json"), "--no-browser"])
    assert result.exit_code == 1 and "run.json: not a folder" in result.output, result.output


def test_ground_is_the_dsm_hillshade_on_the_dtm_in_the_glb_frame(delft_run):
    out = delft_run.out_dir
    files = site_files(out)
    info = json.loads(files["/run/scene.json"][0])
    origin = np.array(json.loads((out / "run.json").read_text(encoding="utf-8"))["local_frame_origin"])
    assert info["origin"] == origin.tolist() == _glb_document(out / "buildings.glb")["scenes"][0]["extras"]["recon3d"]["origin"]
    dsm, dtm = read_raster(out / "dsm.tif"), read_raster(out / "dtm.tif")
    ground = info["ground"]
    assert ground["kind"] == "hillshade"
    west, south, east, north = dsm.bounds
    np.testing.assert_allclose(ground["extent"], [west - origin[0], south - origin[1], east - origin[0], north - origin[1]])
    rows, cols = ground["heights"]["rows"], ground["heights"]["cols"]
    z = np.array(ground["heights"]["z"]).reshape(rows, cols)
    assert max(rows, cols) == 256
    # corners of the height grid are the DTM's corner cells, heights relative to the origin
    corners = dtm.data[[0, 0, -1, -1], [0, -1, 0, -1]] - origin[2]
    finite = np.isfinite(corners)
    np.testing.assert_allclose(z[[0, 0, -1, -1], [0, -1, 0, -1]][finite], corners[finite], atol=0.005)
    texture = cv2.imdecode(np.frombuffer(files["/run/ground.png"][0], np.uint8), cv2.IMREAD_COLOR)
    scale = min(1.0, 2048 / max(dsm.shape))
    assert texture.shape[:2] == (round(dsm.shape[0] * scale), round(dsm.shape[1] * scale))
    assert files["/run/buildings.glb"][0] == (out / "buildings.glb").read_bytes()


def test_orthophoto_replaces_the_hillshade(delft_run, tmp_path):
    import rasterio
    from affine import Affine

    for name in ("buildings.glb", "run.json", "dtm.tif"):
        shutil.copy(delft_run.out_dir / name, tmp_path / name)
    dtm = read_raster(tmp_path / "dtm.tif")
    west, _, _, north = dtm.bounds
    rgb = np.zeros((3, 40, 60), np.uint8)
    rgb[0, :20], rgb[1, 20:], rgb[2, :, :30] = 200, 150, 100  # red north, green south, blue west
    profile = {"driver": "GTiff", "width": 60, "height": 40, "count": 3, "dtype": "uint8", "crs": "EPSG:28992",
               "transform": Affine(2.0, 0.0, west + 10, 0.0, -2.0, north - 10)}
    with rasterio.open(tmp_path / "ortho.tif", "w", **profile) as dst:
        dst.write(rgb)
    files = site_files(tmp_path)
    ground = json.loads(files["/run/scene.json"][0])["ground"]
    origin = json.loads((tmp_path / "run.json").read_text(encoding="utf-8"))["local_frame_origin"]
    assert ground["kind"] == "orthophoto"
    np.testing.assert_allclose(ground["extent"], [west + 10 - origin[0], north - 90 - origin[1],
                                                  west + 130 - origin[0], north - 10 - origin[1]])
    texture = cv2.imdecode(np.frombuffer(files["/run/ground.png"][0], np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    np.testing.assert_array_equal(texture, np.moveaxis(rgb, 0, -1))


def test_serves_only_the_prepared_files(served):
    with urllib.request.urlopen(served.url + "run/scene.json") as answer:
        assert answer.headers["Content-Type"] == "application/json"
    for path in ("run.json", "run/../run.json", "run/dsm.tif"):
        with pytest.raises(urllib.error.HTTPError) as caught:
            urllib.request.urlopen(served.url + path)
        assert caught.value.code == 404


def test_busy_port_is_replaced_and_ctrl_c_stops(delft_run):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        view = subprocess.Popen([sys.executable, "-m", "recon3d", "view", str(delft_run.out_dir), "--port", str(port),
                                 "--no-browser"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                # Ctrl-C acts even when the suite runs as a background job, which ignores it
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            with selectors.DefaultSelector() as waiting:  # the first line, or fail rather than hang
                waiting.register(view.stdout, selectors.EVENT_READ)
                assert waiting.select(timeout=120), "recon3d view printed nothing"
            line = view.stdout.readline()
            assert line.startswith(f"serving {delft_run.out_dir} at http://127.0.0.1:"), line
            url = line.split(" at ")[1].split()[0]
            assert not url.endswith(f":{port}/")
            with urllib.request.urlopen(url) as answer:
                assert b"viewer.js" in answer.read()
            view.send_signal(signal.SIGINT)
            out, err = view.communicate(timeout=30)
        finally:
            view.kill()
    assert view.returncode == 0, err
    assert f"port {port} is in use: serving on port {url.rsplit(':', 1)[1].strip('/')} instead" in err
    assert out.strip() == "stopped"


def test_three_bundle_is_the_pinned_build(tmp_path):
    """static/three.min.js is what `npm run build-viewer --prefix tools` makes of the pinned three.js."""
    esbuild = ROOT / "tools" / "node_modules" / ".bin" / "esbuild"
    if shutil.which("node") is None:
        pytest.skip("node is not installed: the three.js bundle cannot be rebuilt")
    if not esbuild.exists():
        pytest.fail("esbuild is not installed: run `npm ci --prefix tools` (README, Install)")
    script = json.loads((ROOT / "tools" / "package.json").read_text(encoding="utf-8"))["scripts"]["build-viewer"]
    args = [a if not a.startswith("--outfile=") else f"--outfile={tmp_path / 'three.min.js'}" for a in script.split()[1:]]
    subprocess.run([str(esbuild), *args, "--log-level=warning"], cwd=ROOT / "tools", check=True, timeout=120)
    assert (tmp_path / "three.min.js").read_bytes() == (STATIC / "three.min.js").read_bytes()
    assert "MIT License" in (STATIC / "three.LICENSE").read_text(encoding="utf-8")


@pytest.mark.slow
def test_page_draws_the_buildings_and_a_click_shows_the_id(delft_run, served):
    browser = _chromium()
    from playwright.sync_api import sync_playwright

    extras = _building_extras(delft_run.out_dir)
    lods = {lod: sum(e["lod"] == lod for e in extras.values()) for lod in {e["lod"] for e in extras.values()}}
    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=browser, args=WEBGL_FLAGS)
        try:
            page = chromium.new_page(viewport={"width": 1200, "height": 800})
            page.goto(served.url)
            page.wait_for_function("window.recon3dViewer && (window.recon3dViewer.ready || window.recon3dViewer.error)",
                                   timeout=60_000)
            assert page.evaluate("window.recon3dViewer.error") is None
            assert sorted(page.evaluate("window.recon3dViewer.ids")) == sorted(extras)
            assert page.inner_text("#status").startswith(f"{len(extras)} buildings loaded; ground: hillshade")
            legend = page.inner_text("#legend")
            for lod, n in lods.items():
                assert f"LoD {lod}: {n}" in legend

            shot = cv2.imdecode(np.frombuffer(page.locator("#view").screenshot(), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
            background = np.all(np.abs(shot.astype(int) - BACKGROUND) <= 2, axis=2)
            assert 0.2 < background.mean() < 0.9  # the site fills part of the view, not all of it
            assert shot[~background].std() > 20  # shaded ground and buildings, not one flat colour
            lod_colour = page.evaluate(f"window.recon3dViewer.colour({next(iter(extras))!r})")
            assert _share_near(shot, lod_colour) > 0.005  # buildings in their LoD colour are drawn

            largest = sorted(extras, key=lambda i: -extras[i]["area"])[:3]
            for building in largest:
                point = page.evaluate(f"window.recon3dViewer.project({building!r})")
                page.mouse.click(point["x"], point["y"])
                assert page.evaluate("window.recon3dViewer.selected()") == building
                panel = page.inner_text("#building")
                assert f"id\t{building}" in panel, panel
                assert f"status\t{extras[building]['status']}" in panel
            page.mouse.click(5, 5)  # the sky: nothing selected
            assert page.evaluate("window.recon3dViewer.selected()") is None

            page.click("#by-quality")
            assert page.evaluate("window.recon3dViewer.mode()") == "quality"
            not_ok = sum(e["status"] != "ok" for e in extras.values())
            assert f"status not ok (fallback): {not_ok}" in page.inner_text("#legend")
            colours = {i: page.evaluate(f"window.recon3dViewer.colour({i!r})") for i in extras}
            fallback = {colours[i] for i, e in extras.items() if e["status"] != "ok"}
            assert len(fallback) <= 1 and not fallback & {colours[i] for i, e in extras.items() if e["status"] == "ok"}
            assert colours[next(iter(extras))] != lod_colour
        finally:
            chromium.close()


def _share_near(image: np.ndarray, hex_colour: str, tolerance: int = 60) -> float:
    """Share of the (rows, cols, 3) RGB image's pixels within ``tolerance`` (sum of |diff|) of the colour, lit or in shade."""
    rgb = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)], float)
    pixels = image.reshape(-1, 3).astype(float)
    brightness = pixels.sum(axis=1, keepdims=True) / max(rgb.sum(), 1)  # lit faces brighter, walls darker
    return float((np.abs(pixels - rgb * brightness).sum(axis=1) < tolerance).mean())


@pytest.fixture(scope="module")
def stereo_view_run(tmp_path_factory):
    """A rendered frame-stereo scene run end to end: it has buildings_textured.glb."""
    from recon3d.pipeline.run import run
    from recon3d.synthetic import write_scene

    folder = tmp_path_factory.mktemp("viewer_stereo") / "scene"
    write_scene(folder, seed=6, size=100.0, gsd=0.3, image_size=(600, 450))
    return run(folder, folder.parent / "out")


def test_photo_mode_shows_the_textured_model_and_still_picks(stereo_view_run):
    """A stereo run's page offers the photo mode: the buildings in their LoD colours give
    way to the textures of buildings_textured.glb, and a click still selects a building."""
    browser = _chromium()
    from playwright.sync_api import sync_playwright

    out = stereo_view_run.out_dir
    files = site_files(out)
    assert json.loads(files["/run/scene.json"][0])["textured"] is True
    assert files["/run/buildings_textured.glb"][0] == (out / "buildings_textured.glb").read_bytes()
    extras = _building_extras(out)
    server = start_server(out)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with sync_playwright() as p:
            chromium = p.chromium.launch(executable_path=browser, args=WEBGL_FLAGS)
            page = chromium.new_page(viewport={"width": 1200, "height": 800})
            page.goto(server.url)
            page.wait_for_function("window.recon3dViewer && (window.recon3dViewer.ready || window.recon3dViewer.error)",
                                   timeout=60_000)
            assert page.evaluate("window.recon3dViewer.error") is None
            assert page.is_visible("#by-photo")

            def shot():
                return cv2.imdecode(np.frombuffer(page.locator("#view").screenshot(), np.uint8),
                                    cv2.IMREAD_COLOR)[..., ::-1]

            roofs = {i: page.evaluate(f"window.recon3dViewer.project({i!r})") for i in extras}
            box = page.locator("#view").bounding_box()

            def patch(image, point):  # mean colour of the 5 x 5 pixels at a building's roof point
                c, r = int(point["x"] - box["x"]), int(point["y"] - box["y"])
                return image[r - 2:r + 3, c - 2:c + 3].reshape(-1, 3).astype(float).mean(axis=0)

            before = shot()
            page.click("#by-photo")
            assert page.evaluate("window.recon3dViewer.mode()") == "photo"
            after = shot()
            # every roof point in its LoD colour before, in the colours of its images after
            changed = [np.abs(patch(after, q) - patch(before, q)).sum() > 40 for q in roofs.values()]
            assert np.mean(changed) >= 0.8, changed
            assert page.evaluate("window.recon3dViewer.photo()") == {"shown": True, "buildings": len(extras)}
            largest = max(extras, key=lambda i: extras[i]["area"])
            point = page.evaluate(f"window.recon3dViewer.project({largest!r})")
            page.mouse.click(point["x"], point["y"])
            assert page.evaluate("window.recon3dViewer.selected()") == largest
            chromium.close()
    finally:
        server.shutdown()
        server.server_close()


def test_a_lidar_run_has_no_photo_mode(delft_run):
    files = site_files(delft_run.out_dir)
    assert json.loads(files["/run/scene.json"][0])["textured"] is False
    assert "/run/buildings_textured.glb" not in files
