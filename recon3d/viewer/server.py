"""The files of the run viewer and the localhost HTTP server that serves them.

Everything the page asks for is prepared once, in memory, before the server starts
(:func:`site_files`): the page itself, ``run/buildings.glb`` as the run wrote it (and
``run/buildings_textured.glb``, the model textured from the images, when the run has
one), ``run/ground.png`` (the texture) and ``run/scene.json`` (frame origin, CRS, where
the ground lies and its heights, in the local frame of the GLB). Nothing else of the
output folder is reachable.

Local frame, as in :mod:`recon3d.io.gltf`: glTF is Y up, so a world point (x, y, z)
is at ``(x - x0, z - z0, -(y - y0))`` in the page, ``(x0, y0, z0)`` the origin in the
GLB's scene extras.
"""

from __future__ import annotations

import errno
import json
import logging
import struct
import threading
import webbrowser
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

from recon3d.errors import InputError

log = logging.getLogger(__name__)

#: Files a finished run must hold for the viewer.
REQUIRED = ("buildings.glb", "run.json")

#: The page's own files, shipped as package data: URL path -> (file, content type).
STATIC = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/viewer.js": ("viewer.js", "text/javascript; charset=utf-8"),
    "/three.min.js": ("three.min.js", "text/javascript; charset=utf-8"),
}
STATIC_DIR = Path(__file__).with_name("static")

#: Longest side of the ground texture (px) and of the ground's height grid (samples).
MAX_TEXTURE = 2048
MAX_HEIGHT_SAMPLES = 256

#: Grey level of the darkest hillshade pixel on the ground texture (0 in report.html),
#: and the colour of cells without data (water, in LiDAR).
SHADE_FLOOR = 80
NO_DATA_RGB = (172, 188, 204)


def check_run(out_dir: str | Path) -> Path:
    """``out_dir`` as a Path; :class:`InputError` naming what is missing when it is not a finished run."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        problem = "not a folder" if out_dir.exists() else "no such folder"
        raise InputError(f"{out_dir}: {problem} (give the output folder of `recon3d run`)")
    missing = [name for name in REQUIRED if not (out_dir / name).is_file()]
    if missing:
        raise InputError(f"{out_dir}: not a finished recon3d run: {' and '.join(missing)} missing")
    return out_dir


def site_files(out_dir: str | Path) -> dict[str, tuple[bytes, str]]:
    """Every URL path the viewer serves for the run in ``out_dir``, with its bytes and content type."""
    out_dir = check_run(out_dir)
    glb = (out_dir / "buildings.glb").read_bytes()
    origin = frame_origin(out_dir, glb)
    files = {path: ((STATIC_DIR / name).read_bytes(), kind) for path, (name, kind) in STATIC.items()}
    files["/run/buildings.glb"] = (glb, "model/gltf-binary")
    ground = ground_layer(out_dir, origin)
    if ground is not None:
        files["/run/ground.png"] = (ground.pop("png"), "image/png")
    textured = out_dir / "buildings_textured.glb"
    if textured.is_file():
        files["/run/buildings_textured.glb"] = (textured.read_bytes(), "model/gltf-binary")
    info = {"title": out_dir.resolve().name, "origin": origin.tolist(), "crs": _glb_extras(glb).get("crs"),
            "ground": ground, "textured": textured.is_file()}
    files["/run/scene.json"] = (json.dumps(info).encode("utf-8"), "application/json")
    return files


def _glb_extras(glb: bytes) -> dict:
    """The ``recon3d`` extras of the GLB's scene ({} when absent or unreadable)."""
    try:
        length, kind = struct.unpack_from("<II", glb, 12)
        document = json.loads(glb[20:20 + length]) if kind == 0x4E4F534A else {}
    except (struct.error, ValueError):
        return {}
    scenes = document.get("scenes") or [{}]
    return scenes[document.get("scene", 0)].get("extras", {}).get("recon3d", {})


def frame_origin(out_dir: Path, glb: bytes) -> np.ndarray:
    """(3,) float64 origin of the local frame: the GLB's scene extras, else run.json ``local_frame_origin``."""
    origin = _glb_extras(glb).get("origin")
    if origin is None:
        try:
            origin = json.loads((out_dir / "run.json").read_text(encoding="utf-8")).get("local_frame_origin")
        except ValueError as exc:
            raise InputError(f"{out_dir / 'run.json'}: not JSON ({exc})") from None
    if origin is None or len(origin) != 3:
        raise InputError(f"{out_dir / 'buildings.glb'}: no local frame origin (scene extras recon3d.origin), "
                         "nor in run.json (local_frame_origin)")
    return np.asarray(origin, dtype=float)


def ground_layer(out_dir: Path, origin: np.ndarray) -> dict | None:
    """The ground under the buildings: texture, extent and heights in the local frame.

    The texture is ``ortho.tif`` when the run has one, else the hillshade of ``dsm.tif``;
    the heights are the DTM's (the DSM's without one) on a grid of at most
    :data:`MAX_HEIGHT_SAMPLES` per side spanning the texture's extent, row 0 north.

    Returns
    -------
    dict or None
        ``kind`` ("orthophoto" or "hillshade"), ``png`` (bytes), ``extent`` [west, south,
        east, north] local, ``heights`` {``rows``, ``cols``, ``z``: rows*cols local
        heights, row-major}; None when the run has no texture or no heights.
    """
    from recon3d.io.geotiff import read_raster

    ortho, dsm, dtm = out_dir / "ortho.tif", out_dir / "dsm.tif", out_dir / "dtm.tif"
    heights_path = next((p for p in (dtm, dsm) if p.is_file()), None)
    if heights_path is None:
        log.warning("%s: no dtm.tif nor dsm.tif: the buildings are shown without ground", out_dir)
        return None
    if ortho.is_file():
        image, transform, kind = *_read_rgb(ortho), "orthophoto"
    elif dsm.is_file():
        raster = read_raster(dsm)
        image, transform, kind = _ground_shade(raster), raster.transform, "hillshade"
    else:
        log.warning("%s: no ortho.tif nor dsm.tif: the buildings are shown without ground", out_dir)
        return None
    rows, cols = image.shape[:2]
    west, north = transform.c, transform.f  # north-up grids, as recon3d writes them
    east, south = west + cols * transform.a, north + rows * transform.e
    z = _heights(read_raster(heights_path), (west, south, east, north)) - origin[2]
    return {
        "kind": kind,
        "png": _png(image),
        "extent": [west - origin[0], south - origin[1], east - origin[0], north - origin[1]],
        "heights": {"rows": z.shape[0], "cols": z.shape[1], "z": np.round(z, 2).ravel().tolist()},
    }


def _ground_shade(dsm) -> np.ndarray:
    """(rows, cols, 3) uint8: the DSM's hillshade, softened so the buildings stand out, empty cells blue-grey."""
    from recon3d.report.maps import hillshade

    shade = SHADE_FLOOR + hillshade(dsm.data.astype(float), dsm.resolution) * (1 - SHADE_FLOOR / 255)
    image = np.repeat(shade.astype(np.uint8)[..., None], 3, axis=2)
    image[~np.isfinite(dsm.data)] = NO_DATA_RGB
    return image


def _read_rgb(path: Path):
    """(rows, cols, 3) uint8 image of a raster's first three bands (one band: grey) and its transform."""
    import rasterio

    with rasterio.open(path) as src:
        bands = src.read(list(range(1, min(src.count, 3) + 1)), masked=True)
        transform = src.transform
    data = bands.astype(float).filled(np.nan)
    if bands.dtype != np.uint8:  # 16-bit or float imagery: stretch the 2nd-98th percentiles
        lo, hi = np.nanpercentile(data, [2, 98]) if np.isfinite(data).any() else (0.0, 1.0)
        data = (data - lo) / max(hi - lo, 1e-12) * 255
    image = np.clip(np.nan_to_num(data), 0, 255).astype(np.uint8)
    image = np.repeat(image, 3, axis=0) if len(image) == 1 else image
    return np.moveaxis(image, 0, -1), transform


def _heights(raster, extent) -> np.ndarray:
    """(n, m) float64 raster values at a grid of points spanning ``extent`` corner to corner.

    Nearest cell; empty cells take the nearest filled cell's value.
    """
    from scipy import ndimage

    west, south, east, north = extent
    step = max(east - west, north - south) / (MAX_HEIGHT_SAMPLES - 1)
    cols = max(2, int(np.ceil((east - west) / step)) + 1)
    rows = max(2, int(np.ceil((north - south) / step)) + 1)
    x, y = np.meshgrid(np.linspace(west, east, cols), np.linspace(north, south, rows))
    row, col = raster.rowcol(x, y)
    row, col = np.clip(row, 0, raster.shape[0] - 1), np.clip(col, 0, raster.shape[1] - 1)
    data = raster.data.astype(float)
    empty = ~np.isfinite(data)
    if empty.all():
        return np.zeros((rows, cols))
    if empty.any():
        nearest = ndimage.distance_transform_edt(empty, return_distances=False, return_indices=True)
        data = data[tuple(nearest)]
    return data[row, col]


def _png(image: np.ndarray) -> bytes:
    """PNG bytes of a grey (rows, cols) or RGB (rows, cols, 3) uint8 image, at most :data:`MAX_TEXTURE` px wide or high."""
    import cv2

    scale = MAX_TEXTURE / max(image.shape[:2])
    if scale < 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    if image.ndim == 3:
        image = image[..., ::-1]  # OpenCV writes BGR
    ok, data = cv2.imencode(".png", np.ascontiguousarray(image))
    return data.tobytes()


class _Handler(BaseHTTPRequestHandler):
    """Answers GET with one of the server's prepared files, 404 otherwise."""

    def do_GET(self) -> None:  # noqa: N802 (the name http.server calls)
        found = self.server.files.get(urlsplit(self.path).path)
        if found is None:
            self.send_error(404)
            return
        body, kind = found
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")  # another run may be served on this port next
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args) -> None:  # noqa: A002 (http.server's signature)
        log.debug("%s %s", self.address_string(), format % args)


class ViewerServer(ThreadingHTTPServer):
    """A localhost HTTP server over a fixed set of files (:func:`site_files`)."""

    daemon_threads = True  # a browser's open connection never holds up Ctrl-C

    def __init__(self, files: dict[str, tuple[bytes, str]], port: int) -> None:
        self.files = files
        super().__init__(("127.0.0.1", port), _Handler)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_port}/"


def start_server(out_dir: str | Path, port: int | None = None) -> ViewerServer:
    """A bound (not yet serving) :class:`ViewerServer` for the run in ``out_dir``.

    ``port`` None takes a free port; a port already in use is replaced by a free one,
    with a warning naming both.
    """
    files = site_files(out_dir)
    try:
        return ViewerServer(files, port or 0)
    except OSError as exc:
        if exc.errno != errno.EADDRINUSE:
            raise InputError(f"cannot serve on port {port}: {exc.strerror}") from None
    server = ViewerServer(files, 0)
    log.warning("port %d is in use: serving on port %d instead", port, server.server_port)
    return server


def serve(server: ViewerServer, *, open_browser: bool = True) -> None:
    """Serve until Ctrl-C (or SIGTERM raised as an exception), then close the socket.

    The browser is started from a thread: a console browser (lynx, w3m) blocks until
    it quits, and the server must answer it meanwhile.
    """
    if open_browser:
        threading.Thread(target=_open_browser, args=(server.url,), daemon=True).start()
    try:
        server.serve_forever()
    finally:
        server.server_close()


def _open_browser(url: str) -> None:
    if not webbrowser.open(url):
        log.warning("no web browser found: open %s yourself", url)
