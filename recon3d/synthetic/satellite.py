"""Synthetic satellite stereo pairs: pushbroom images of a known city, with fitted RPCs.

A :class:`PushbroomCamera` flies a straight orbit line high above the scene and takes
one image row per step, looking forward or backward along track (the pitch that makes
the stereo base) and slightly across (roll). Each pixel is rendered with one ray, as
the frame renderer does, so the truth is exact. The camera is then described the way a
satellite provider describes it: an RPC00B model fitted to its projection over the
scene's longitude, latitude and height range (residuals of a few thousandths of a
pixel), written into GeoTIFF RPC tags beside 12-bit panchromatic images. ``recon3d run
img1.tif img2.tif`` reads the pair like any Pleiades pair.

Layout of :func:`write_satellite_scene`::

    img1.tif img2.tif      uint16 panchromatic (12 bit), RPC tags (full scenes, no crop)
    truth/                 dsm.tif dtm.tif views.tif checkpoints.csv footprints.geojson
                           ... (as for frame scenes, in the scene's UTM zone)
    truth/scene.json       the survey's parameters and the city's
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pyproj

from recon3d.io import atomic_path
from recon3d.io.rpc import RPCModel, _terms
from recon3d.synthetic.city import SyntheticCity, make_city, nice_cell_size
from recon3d.synthetic.render import Lighting, render

log = logging.getLogger(__name__)

__all__ = ["SATELLITE_SCENES", "PushbroomCamera", "SatelliteSpec", "fit_rpc", "satellite_pair", "write_satellite_scene"]


@dataclass(frozen=True)
class PushbroomCamera:
    """A linear-array camera on a straight orbit, in a local metric frame (z up).

    Row ``r`` is taken from ``start + r * step``; the sensor line looks along the
    rotation ``R`` (camera x across track, y along track, z the viewing direction), so
    pixel (row, col) sees along ``R.T @ [(col + 0.5 - cx) / focal, 0, 1]`` (pixel
    centres at +0.5, as :class:`~recon3d.synthetic.render.PinholeCamera`).

    Attributes
    ----------
    start : (3,) float
        Projection centre of row 0.
    step : (3,) float
        Movement per row.
    R : (3, 3) float
        World to camera rotation.
    focal, cx : float
        Across-track focal length and principal point (pixels).
    width, height : int
    name : str
    ray_start : float
        Height at which rendered rays start (just above the scene: float32 ray casting
        keeps centimetres there, not 700 km up).
    """

    start: np.ndarray
    step: np.ndarray
    R: np.ndarray
    focal: float
    cx: float
    width: int
    height: int
    name: str = ""
    ray_start: float = 500.0

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) pixel coordinates (col, row, centres at +0.5) and (n,) depths of (n, 3) points."""
        p = np.asarray(xyz, np.float64) - self.start
        along, step_along = p @ self.R[1], float(self.R[1] @ self.step)
        row = along / step_along  # the row whose sensor line holds the point
        q = p - row[:, None] * self.step
        depth = q @ self.R[2]
        col = self.focal * (q @ self.R[0]) / depth + self.cx
        return np.column_stack([col, row + 0.5]), depth

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """(n, 3) unit world directions of the rays through (n, 2) pixel coordinates."""
        uv = np.asarray(uv, np.float64)
        d = np.column_stack([(uv[:, 0] - self.cx) / self.focal, np.zeros(len(uv)), np.ones(len(uv))]) @ self.R
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def origins(self, uv: np.ndarray) -> np.ndarray:
        """(n, 3) where the rays of the pixels start: on their line, at height ``ray_start``."""
        uv = np.asarray(uv, np.float64)
        centre = self.start + (uv[:, 1:2] - 0.5) * self.step
        d = self.rays(uv)
        t = (self.ray_start - centre[:, 2]) / d[:, 2]
        return centre + t[:, None] * d

    def pixel_centres(self) -> np.ndarray:
        c, r = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        return np.column_stack([c.ravel(), r.ravel()])


@dataclass(frozen=True)
class SatelliteSpec:
    """One synthetic satellite stereo pair.

    Attributes
    ----------
    seed : int
    terrain, layout, trees : str
        The city (:func:`~recon3d.synthetic.city.make_city`).
    size : float
        Side of the city area, metres; the images cover it and a margin.
    gsd : float
        Ground sample distance at nadir, metres.
    base_to_height : float
        The pair's base over the orbit height: the two images look forward and back
        along track by half its angle each.
    roll : float
        Degrees the sensor looks across track (both images).
    heading : float
        Orbit direction, degrees from north.
    altitude : float
        Orbit height, metres.
    centre_lonlat : (float, float)
        Where on Earth the scene lies (the UTM zone follows).
    name : str
    """

    seed: int = 0
    terrain: str = "mountain"
    layout: str = "sparse"
    trees: str = "beside"
    size: float = 400.0
    gsd: float = 0.5
    base_to_height: float = 0.4
    roll: float = 3.0
    heading: float = 190.0
    altitude: float = 694_000.0
    centre_lonlat: tuple[float, float] = (6.5, 45.0)
    name: str = ""

    @property
    def crs(self) -> pyproj.CRS:
        lon, lat = self.centre_lonlat
        return pyproj.CRS.from_epsg(32600 + int((lon + 180) // 6) + 1 + (0 if lat >= 0 else 100))


#: The terrains of issue 16's targets: steep mountains with a village, a town on hills,
#: a flat desert.
SATELLITE_SCENES = {
    "mountain": SatelliteSpec(seed=21, terrain="mountain", layout="sparse", name="mountain"),
    "town": SatelliteSpec(seed=22, terrain="hilly", layout="regular", base_to_height=0.3, heading=170.0,
                          centre_lonlat=(31.1, 29.98), name="town"),
    "desert": SatelliteSpec(seed=23, terrain="flat", layout="none", trees="none", base_to_height=0.5, roll=-5.0,
                            centre_lonlat=(-116.0, 36.0), name="desert"),
}


def satellite_pair(spec: SatelliteSpec, city: SyntheticCity) -> tuple[PushbroomCamera, PushbroomCamera]:
    """The forward and backward looking cameras over the city's centre (local frame)."""
    half = math.atan(spec.base_to_height / 2)
    heading = math.radians(spec.heading)
    along = np.array([math.sin(heading), math.cos(heading), 0.0])
    across = np.array([math.cos(heading), -math.sin(heading), 0.0])
    centre = np.array([city.size / 2, city.size / 2, float(city.ground_height(*(np.array([city.size / 2]) + o for o in city.origin[:2]))[0] - city.origin[2])])
    focal = spec.altitude / spec.gsd
    pixels = int(math.ceil(spec.size * 1.1 / spec.gsd / 8) * 8)
    cams = []
    for k, pitch in enumerate((half, -half)):
        view = np.array([0.0, 0.0, -1.0])
        view = _turn(view, across, pitch)  # forward (+) or backward along track
        view = _turn(view, along, math.radians(spec.roll))
        x_axis = np.cross(view, along)
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(view, x_axis)
        R = np.stack([x_axis, y_axis, view])
        # the line through the centre at mid-image: where the sensor sees the centre at row height/2
        distance = spec.altitude / abs(view[2])
        mid = centre - view * distance
        step = -along * spec.gsd * (1 if y_axis @ along < 0 else -1)
        start = mid - (pixels / 2) * step
        cams.append(PushbroomCamera(start, step, R, focal, pixels / 2, pixels, pixels, f"img{k + 1}.tif",
                                    ray_start=float(centre[2] + 600.0)))
    return tuple(cams)


def _turn(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``v`` rotated by ``angle`` radians about the unit ``axis`` (Rodrigues)."""
    axis = axis / np.linalg.norm(axis)
    return v * math.cos(angle) + np.cross(axis, v) * math.sin(angle) + axis * (axis @ v) * (1 - math.cos(angle))


def fit_rpc(camera: PushbroomCamera, to_lonlat, heights: tuple[float, float], extent, *, n: int = 15) -> tuple[RPCModel, float]:
    """An RPC00B model of ``camera`` over a ground box, and its largest residual (pixels).

    Parameters
    ----------
    camera : PushbroomCamera
    to_lonlat : callable
        (x, y) local -> (lon, lat) degrees.
    heights : (float, float)
        Local height range to cover (also the ellipsoidal heights the model uses).
    extent : (x0, y0, x1, y1)
        Local ground box to cover.
    n : int
        Grid nodes per horizontal axis (``n // 2`` in height).

    The numerator and denominator coefficients come from the usual linearised least
    squares (denominators' constant term 1), solved per image axis.
    """
    x0, y0, x1, y1 = extent
    gx, gy, gz = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n), np.linspace(*heights, max(3, n // 2)), indexing="ij")
    xyz = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    uv, _ = camera.project(xyz)
    col, row = uv[:, 0] - 0.5, uv[:, 1] - 0.5  # RPC: (0, 0) is the top-left pixel's centre
    lon, lat = to_lonlat(xyz[:, 0], xyz[:, 1])
    h = xyz[:, 2]

    def norm(v):
        off = 0.5 * (v.max() + v.min())
        scale = max(0.5 * (v.max() - v.min()), 1e-9)
        return off, scale

    (lon_o, lon_s), (lat_o, lat_s), (h_o, h_s) = norm(lon), norm(lat), norm(h)
    (r_o, r_s), (c_o, c_s) = norm(row), norm(col)
    L, P, H = (lon - lon_o) / lon_s, (lat - lat_o) / lat_s, (h - h_o) / h_s
    T = _terms(L, P, H)  # (20, m)
    coeffs = {}
    for name, target in (("line", (row - r_o) / r_s), ("samp", (col - c_o) / c_s)):
        A = np.concatenate([T.T, -target[:, None] * T[1:].T], axis=1)
        x, *_ = np.linalg.lstsq(A, target, rcond=None)
        coeffs[f"{name}_num"] = x[:20]
        coeffs[f"{name}_den"] = np.r_[1.0, x[20:]]
    model = RPCModel(**coeffs, line_off=r_o, line_scale=r_s, samp_off=c_o, samp_scale=c_s,
                     lat_off=lat_o, lat_scale=lat_s, lon_off=lon_o, lon_scale=lon_s,
                     height_off=h_o, height_scale=h_s)
    rr, cc = model.project(lon, lat, h)
    return model, float(np.max(np.hypot(rr - row, cc - col)))


def write_satellite_scene(folder: str | Path, spec: SatelliteSpec, *, lighting: Lighting = Lighting()) -> dict:
    """Render a pair of :class:`SatelliteSpec`, fit their RPCs and write the images and truth.

    Returns
    -------
    dict
        Paths of the two images, the cameras, the city and the RPC fit residuals.
    """
    from recon3d.synthetic.scene import _write_json, _write_truth

    folder = Path(folder)
    start = time.perf_counter()
    origin = pyproj.Transformer.from_crs(4326, spec.crs, always_xy=True).transform(*spec.centre_lonlat)
    origin = (math.floor(origin[0] - spec.size / 2), math.floor(origin[1] - spec.size / 2), 0.0)
    margin = spec.size * 0.3 + 200.0
    city = make_city(spec.seed, size=spec.size, margin=margin, origin=origin, crs=f"EPSG:{spec.crs.to_epsg()}",
                     terrain=spec.terrain, layout=spec.layout, trees=spec.trees)
    cams = satellite_pair(spec, city)
    to_geo = pyproj.Transformer.from_crs(spec.crs, 4326, always_xy=True)

    def to_lonlat(x, y):
        return to_geo.transform(np.asarray(x) + origin[0], np.asarray(y) + origin[1])

    z = city.vertices[:, 2]
    heights = (float(z.min()) - 20.0, float(z.max()) + 20.0)
    pad = 0.25 * spec.size
    extent = (-pad, -pad, spec.size + pad, spec.size + pad)
    folder.mkdir(parents=True, exist_ok=True)
    residuals, paths = [], []
    for k, cam in enumerate(cams):
        dn = _panchromatic(city, cam, lighting, spec, seed=spec.seed + 97 * k)
        model, residual = fit_rpc(cam, to_lonlat, heights, extent)
        residuals.append(residual)
        paths.append(folder / cam.name)
        _write_geotiff(folder / cam.name, dn, model)
    cell = nice_cell_size(spec.gsd)
    _write_truth(folder / "truth", city, cell, cams)
    _write_json(folder / "truth" / "scene.json", {
        "generator": "recon3d.synthetic.satellite", "spec": asdict(spec), "city": city.params,
        "cell_size": cell, "rpc_fit_residual_px": [round(r, 5) for r in residuals],
    })
    log.info("synthetic satellite pair %s: %.1f s, RPC residuals %s px", folder, time.perf_counter() - start, residuals)
    return {"images": paths, "cameras": cams, "city": city, "rpc_residual_px": residuals}


def _panchromatic(city: SyntheticCity, cam: PushbroomCamera, lighting: Lighting, spec: SatelliteSpec, *, seed: int) -> np.ndarray:
    """(height, width) uint16: a 12-bit panchromatic image as a pushbroom sensor records it.

    One ray per pixel cannot integrate texture finer than the pixel (it would alias into
    noise that differs between the views, which no real sensor shows), so the texture's
    finest detail is two ground samples and the sensor's MTF is a Gaussian blur of
    0.5 px. Radiance fills a narrow part of the 12-bit range, as on Pleiades or
    WorldView panchromatic images (dark ground, most of the range left for bright
    roofs), with photon noise growing with the signal.
    """
    import cv2

    shot = render(city, cam, lighting=dataclasses.replace(lighting, noise_sigma=0.0),
                  texture_scale=2.0 * spec.gsd, seed=spec.seed)
    grey = shot.image.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    grey = cv2.GaussianBlur(grey, (0, 0), 0.5)
    signal = 180.0 + 3.0 * grey  # digital numbers, about 180 to 950 of 4095
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 61]))
    dn = signal + rng.normal(0.0, 1.0, signal.shape) * np.sqrt(0.25 * signal)
    return np.clip(np.rint(dn), 0, 4095).astype(np.uint16)


def _write_geotiff(path: Path, data: np.ndarray, model: RPCModel) -> None:
    import rasterio

    rows, cols = data.shape
    profile = {"driver": "GTiff", "width": cols, "height": rows, "count": 1, "dtype": "uint16",
               "compress": "deflate", "tiled": rows >= 256 and cols >= 256}
    if profile["tiled"]:
        profile.update(blockxsize=256, blockysize=256)
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile, rpcs=model.to_rasterio()) as dst:
            dst.write(data, 1)
