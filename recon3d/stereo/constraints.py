"""Vector-constrained matching: what the user already knows about the heights bounds the search.

The classic production line (AutoDEM) matched with 3-D vectors: building outlines with
their roof heights, surveyed spot heights and breaklines, and a coarse elevation model.
Each becomes, on a world grid, the lowest and the highest elevation the visible surface
can have:

============================  ==============================  =========================
source                        lowest surface                  highest surface
============================  ==============================  =========================
coarse DEM (``--dem``)        DEM - ``dem_tolerance``         DEM + tallest object
spot heights, breaklines      their TIN - ``ground_tolerance``  (no bound)
footprints with roof heights  eave - ``roof_tolerance``       ridge + ``roof_tolerance``
============================  ==============================  =========================

(inside an outline shrunk by ``roof_tolerance`` metres, where the roof surely is; where
sources overlap, the tighter bound wins). :func:`pair_bounds` turns them into per-pixel
disparity bounds of a rectified pair by walking each pixel's ray down through the grid:
the surface the pixel sees lies below the highest height the ray may have and above the
highest point where the ray would already be inside the ground or a building. Bounds
from the DEM and the survey hold firmly; those from footprints, which may be out of date,
only weigh on the matching cost (``footprint_weight``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import shapely
from affine import Affine
from rasterio.features import rasterize
from scipy import ndimage

from recon3d.core.raster import Raster, grid_for_bounds
from recon3d.stereo.rectify import RectifiedPair

__all__ = ["ROOF_HEIGHT_FIELDS", "ElevationBounds", "elevation_bounds", "pair_bounds", "roof_range"]

#: Attribute names read as a footprint's highest and lowest roof heights (absolute
#: elevations, the CRS's height units), first match wins, case ignored.
ROOF_HEIGHT_FIELDS = {
    "top": ("ridge_z", "roof_z", "z_max", "max_z", "roof_top", "roof_height", "h_max", "zmax"),
    "bottom": ("eave_z", "z_min", "min_z", "roof_bottom", "eave_height", "h_min", "zmin"),
}


@dataclass
class ElevationBounds:
    """Lowest and highest surface elevation per cell of a world grid.

    Attributes
    ----------
    low, high : (rows, cols) float32
        World heights; NaN where nothing bounds the surface.
    weight : (rows, cols) float32
        How firmly each cell's bounds hold, in [0, 1] (1: they may not be crossed).
    transform : affine.Affine
    sources : dict
        What went in, for run.json.
    """

    low: np.ndarray
    high: np.ndarray
    weight: np.ndarray
    transform: Affine
    sources: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.low.shape

    def sample(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Low, high and weight at world points (nearest cell); NaN and 0 outside the grid."""
        t = self.transform
        c = np.floor((x - t.c) / t.a).astype(np.int64)
        r = np.floor((y - t.f) / t.e).astype(np.int64)
        ok = (r >= 0) & (r < self.shape[0]) & (c >= 0) & (c < self.shape[1])
        lo = np.full(x.shape, np.nan, np.float32)
        hi = np.full(x.shape, np.nan, np.float32)
        wt = np.zeros(x.shape, np.float32)
        lo[ok], hi[ok], wt[ok] = self.low[r[ok], c[ok]], self.high[r[ok], c[ok]], self.weight[r[ok], c[ok]]
        return lo, hi, wt


def roof_range(attributes: dict) -> tuple[float | None, float | None]:
    """(lowest, highest) roof height of a footprint's attributes, None where absent."""
    lower = {k.lower(): v for k, v in attributes.items()}

    def first(names):
        for n in names:
            v = lower.get(n)
            if isinstance(v, int | float) and math.isfinite(v):
                return float(v)
        return None

    return first(ROOF_HEIGHT_FIELDS["bottom"]), first(ROOF_HEIGHT_FIELDS["top"])


def elevation_bounds(
    extent: tuple[float, float, float, float],
    cell: float,
    *,
    dem: Raster | None = None,
    dem_tolerance: float = 2.0,
    max_object_height: float = 40.0,
    ground_points: np.ndarray | None = None,
    ground_tolerance: float = 0.5,
    footprints: list[tuple[shapely.Polygon, float | None, float | None]] | None = None,
    roof_tolerance: float = 1.0,
    footprint_weight: float = 0.5,
) -> ElevationBounds:
    """Bounds of the surface elevation over ``extent`` from whatever the user gave.

    Parameters
    ----------
    extent : (xmin, ymin, xmax, ymax)
        World area to cover.
    cell : float
        Grid cell (CRS units).
    dem : Raster, optional
        Coarse elevation model in the same CRS (terrain heights).
    dem_tolerance : float
        Its vertical error: the surface may lie this far below it.
    max_object_height : float
        The tallest object above the DEM (buildings, trees).
    ground_points : (n, 3) float, optional
        Spot heights and densified breaklines (ground).
    ground_tolerance : float
    footprints : list of (polygon, eave, ridge), optional
        Outlines with their lowest and highest roof heights (None where unknown).
    roof_tolerance : float
        Vertical and horizontal slack of the roof heights and outlines.
    footprint_weight : float
        Weight of the footprints' bounds, in [0, 1].

    Returns
    -------
    ElevationBounds
    """
    transform, shape = grid_for_bounds(*extent, cell)
    low = np.full(shape, -np.inf)
    high = np.full(shape, np.inf)
    weight = np.zeros(shape, np.float32)
    sources: dict = {}
    if dem is not None:
        terrain = _on_grid(dem, transform, shape)
        ok = np.isfinite(terrain)
        low[ok] = terrain[ok] - dem_tolerance
        high[ok] = terrain[ok] + max_object_height
        weight[ok] = 1.0
        sources["dem"] = {"cells_percent": round(100.0 * float(ok.mean()), 1), "tolerance": dem_tolerance,
                          "max_object_height": round(max_object_height, 2)}
    if ground_points is not None and len(ground_points) >= 3:
        terrain = _tin(ground_points, transform, shape)
        ok = np.isfinite(terrain)
        low[ok] = np.maximum(low[ok], terrain[ok] - ground_tolerance)
        weight[ok] = 1.0
        sources["ground_points"] = {"points": len(ground_points), "cells_percent": round(100.0 * float(ok.mean()), 1),
                                    "tolerance": ground_tolerance}
    if footprints:
        used = 0
        for polygon, eave, ridge in footprints:
            if eave is None and ridge is None:
                continue
            core = polygon.buffer(-roof_tolerance)
            if core.is_empty:
                continue
            inside = rasterize([(core, 1)], out_shape=shape, transform=transform).astype(bool)
            if not inside.any():
                continue
            used += 1
            if eave is not None:
                low[inside] = np.maximum(low[inside], eave - roof_tolerance)
            if ridge is not None:
                high[inside] = np.minimum(high[inside], ridge + roof_tolerance)
            weight[inside] = np.where(weight[inside] > 0, np.minimum(weight[inside], footprint_weight), footprint_weight)
        sources["footprints"] = {"with_roof_heights": used, "tolerance": roof_tolerance, "weight": footprint_weight}
    high = np.maximum(high, low)  # contradicting sources: the lowest bound wins
    to_nan = lambda a: np.where(np.isfinite(a), a, np.nan).astype(np.float32)  # noqa: E731
    return ElevationBounds(to_nan(low), to_nan(high), weight, transform, sources)


def pair_bounds(
    pair: RectifiedPair,
    bounds: ElevationBounds,
    offset: np.ndarray,
    z_range: tuple[float, float],
    *,
    step_px: int = 4,
    samples: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel disparity bounds of a rectified pair from elevation bounds.

    Each pixel of a coarse grid (every ``step_px`` pixels) casts its ray from the left
    camera through ``samples`` heights spanning ``z_range`` (world; by default as many
    as keep the most oblique ray's steps within half a grid cell across, 32 to 512). The lowest surface
    the pixel can see lies at the highest height where the ray is already below a lower
    bound (inside the ground or a building); the highest, at the highest height not above
    an upper bound. The coarse bounds are widened to their neighbours' and enlarged to
    the full image.

    Returns
    -------
    low, high : (H, W) float32
        Disparity bounds; NaN where unbounded.
    weight : (H, W) float32
        The weight of the bounds there.
    """
    h, w = pair.left.shape
    ys, xs = np.arange(0, h + step_px - 1, step_px), np.arange(0, w + step_px - 1, step_px)
    gx, gy = np.meshgrid(np.minimum(xs, w - 1).astype(np.float64), np.minimum(ys, h - 1).astype(np.float64))
    rays = np.stack([(gx - pair.cx_left) / pair.focal, (gy - pair.cy) / pair.focal, np.ones_like(gx)], axis=-1)
    direction = rays.reshape(-1, 3) @ pair.rotation  # world direction per unit of rectified depth
    centre = pair.camera_left.center + np.asarray(offset, np.float64)
    z0, z1 = z_range
    if samples is None:
        slope = np.hypot(direction[:, 0], direction[:, 1]) / np.maximum(np.abs(direction[:, 2]), 1e-9)
        step = 0.5 * abs(bounds.transform.a) / max(float(slope.max()), 1e-3)
        samples = int(np.clip(np.ceil((z1 - z0) / step) + 1, 32, 512))
    heights = np.linspace(z1, z0, samples)  # from the top down
    dz = (z1 - z0) / max(samples - 1, 1)
    n = len(direction)
    top = np.full(n, np.nan)   # highest height the ray may have
    floor = np.full(n, np.nan)  # highest height where the ray is already inside something
    wt = np.zeros(n, np.float32)
    going_down = direction[:, 2] < -1e-9
    for z in heights:
        depth = np.where(going_down, (z - centre[2]) / np.where(going_down, direction[:, 2], -1.0), np.nan)
        x, y = centre[0] + depth * direction[:, 0], centre[1] + depth * direction[:, 1]
        lo, hi, weight = bounds.sample(x, y)
        allowed = going_down & ~(z > hi) & np.isnan(top)
        top[allowed] = z
        wt[allowed & (weight > 0)] = weight[allowed & (weight > 0)]
        inside = going_down & (z < lo) & np.isnan(floor)
        floor[inside] = z
        wt[inside] = np.maximum(wt[inside], weight[inside])
    top = np.where(top >= z1, np.nan, top + dz)  # allowed from the first sample on: no upper bound
    floor = floor - dz

    def full(values, kind):
        return _full_size(values.reshape(gx.shape), h, w, step_px, kind)

    low = full(_to_disparity(pair, direction, centre, floor), "min")  # the lowest surface: the least disparity
    high = full(_to_disparity(pair, direction, centre, top), "max")
    return low, high, full(wt, "min")


def _to_disparity(pair: RectifiedPair, direction: np.ndarray, centre: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Disparity of the point of each ray at world height ``z`` (NaN stays NaN)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = (z - centre[2]) / direction[:, 2]
        return np.where(depth > 0, pair.depth_to_disparity(depth), np.nan)


def _full_size(coarse: np.ndarray, h: int, w: int, step: int, kind: str) -> np.ndarray:
    """Coarse-grid values widened over their 3 x 3 neighbours (min or max), to (h, w)."""
    finite = np.isfinite(coarse)
    fill = np.inf if kind == "min" else -np.inf
    filtered = (ndimage.minimum_filter if kind == "min" else ndimage.maximum_filter)(np.where(finite, coarse, fill), size=3)
    unbounded = ndimage.maximum_filter(~finite, size=3)  # a neighbour without bound: none here either
    filtered = np.where(unbounded | ~np.isfinite(filtered), np.nan, filtered).astype(np.float32)
    big = cv2.resize(filtered, (filtered.shape[1] * step, filtered.shape[0] * step), interpolation=cv2.INTER_NEAREST)
    return big[:h, :w]


def _on_grid(source: Raster, transform: Affine, shape: tuple[int, int]) -> np.ndarray:
    """``source`` resampled bilinearly onto a grid of the same CRS."""
    from rasterio.warp import Resampling, reproject

    out = np.full(shape, np.nan, np.float32)
    reproject(
        source.data.astype(np.float32), out, src_transform=source.transform, dst_transform=transform,
        src_nodata=np.nan, dst_nodata=np.nan, resampling=Resampling.bilinear,
        src_crs="EPSG:3857", dst_crs="EPSG:3857",  # one CRS for both: only the grids differ
    )
    return out


def _tin(points: np.ndarray, transform: Affine, shape: tuple[int, int]) -> np.ndarray:
    """Linear interpolation of (n, 3) points over the grid, NaN outside their convex hull."""
    from scipy.interpolate import LinearNDInterpolator

    rows, cols = shape
    c, r = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    x, y = transform.c + c * transform.a, transform.f + r * transform.e
    try:
        return LinearNDInterpolator(points[:, :2], points[:, 2])(x, y)
    except Exception:  # degenerate (collinear) points: no surface
        return np.full(shape, np.nan)
