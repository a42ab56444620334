"""Ground filtering: which points lie on the bare earth.

The default is a simple morphological filter in the style of SMRF (Pingel et al.,
2013): a minimum surface is opened with growing windows; cells that drop by more
than the slope allows for the window are objects; the remaining cells are
interpolated into a provisional terrain, and every point within a slope-dependent
tolerance of it is ground.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from recon3d.config import GroundConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import grid_for_bounds
from recon3d.terrain.dsm import grid_points
from recon3d.terrain.dtm import fill_gaps

log = logging.getLogger(__name__)

__all__ = ["GroundResult", "classify_ground"]


@dataclass
class GroundResult:
    """Ground labels and the parameters the filter used.

    Attributes
    ----------
    is_ground : (n,) bool
    params : dict
        Every parameter, with ``{"value": ..., "reason": ...}`` for those chosen from
        the data, ready for run.json.
    """

    is_ground: np.ndarray
    params: dict = field(default_factory=dict)


def classify_ground(
    cloud: PointCloud, config: GroundConfig, units: Units, cell: float
) -> GroundResult:
    """Label ground points with the method named in ``config``.

    Parameters
    ----------
    cloud : PointCloud
    config : GroundConfig
    units : Units
        Units of the cloud's CRS; metric parameters are converted with it.
    cell : float
        Cell size (CRS units) of the minimum surface when ``config.cell`` is None.
    """
    if config.method == "provider":
        c = cloud.classification
        if c is None or not np.any(c == ASPRS.GROUND):
            from recon3d.errors import InputError

            raise InputError("ground.method='provider' but the input has no ground points (class 2)")
        return GroundResult(c == ASPRS.GROUND, {"method": "provider"})
    return smrf(cloud.xyz, config, units, cell, bounds=cloud.bounds)


def smrf(
    xyz: np.ndarray, config: GroundConfig, units: Units, default_cell: float, *, bounds: np.ndarray | None = None
) -> GroundResult:
    """Simple morphological filter; see the module docstring.

    Parameters
    ----------
    xyz : (n, 3) float
    bounds : (2, 3) float, optional
        Minimum and maximum corner of ``xyz`` when already known.
    """
    params: dict = {"method": "smrf"}
    if config.cell:
        cell, why = units.length(config.cell), "config"
    else:
        cell = max(default_cell, units.length(1.0))
        why = "1 m, or the DSM cell when coarser: finer minimum surfaces only add noise"
    params["cell"] = _chosen(cell, why)
    lo, hi = bounds if bounds is not None else (xyz.min(axis=0), xyz.max(axis=0))
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], cell)
    zmin = grid_points(xyz, transform, shape, reducer="min")
    if not np.isfinite(zmin).any():
        return GroundResult(np.zeros(len(xyz), bool), params)
    zmin = _drop_low_outliers(zmin, units)
    surface = _fill_nearest(zmin)

    if config.max_window:
        window = units.length(config.max_window)
        params["max_window"] = _chosen(config.max_window, "config")
    else:
        window, why = _auto_window(surface, cell, units)
        params["max_window"] = _chosen(round(window * units.horizontal, 1), why)
    if config.slope is not None:
        slope = config.slope
        params["slope"] = _chosen(slope, "config")
    else:
        slope, why = _auto_slope(surface, cell, window, units)
        params["slope"] = _chosen(round(slope, 3), why)

    objects = _progressive_opening(surface, cell, window, slope * units.horizontal / units.vertical)
    objects |= ~np.isfinite(zmin)
    terrain = fill_gaps(surface, ~objects)
    gy, gx = np.gradient(terrain, cell)
    gradient = np.hypot(gx, gy)

    col = np.floor((xyz[:, 0] - transform.c) / transform.a).astype(np.int64)
    row = np.floor((xyz[:, 1] - transform.f) / transform.e).astype(np.int64)
    row = np.clip(row, 0, shape[0] - 1)
    col = np.clip(col, 0, shape[1] - 1)
    from recon3d.core.raster import Raster

    zt = Raster(terrain, transform).sample(xyz[:, 0], xyz[:, 1])
    tolerance = units.height(config.threshold) + config.scalar * gradient[row, col] * cell
    is_ground = np.abs(xyz[:, 2] - zt) <= tolerance
    params.update(threshold=config.threshold, scalar=config.scalar)
    log.info("smrf: %d of %d points ground (%.1f %%)", is_ground.sum(), len(xyz), 100 * is_ground.mean())
    return GroundResult(is_ground, params)


def _chosen(value, reason: str) -> dict:
    return {"value": value, "reason": reason}


def _drop_low_outliers(zmin: np.ndarray, units: Units) -> np.ndarray:
    """NaN out cells far below their neighbourhood (multipath, reflections under water)."""
    filled = _fill_nearest(zmin)
    median = cv2.medianBlur(filled.astype(np.float32), 5)
    low = zmin < median - units.height(2.0)
    if low.any():
        log.info("smrf: %d low-outlier cells ignored", int(low.sum()))
    out = zmin.copy()
    out[low] = np.nan
    return out


def _fill_nearest(data: np.ndarray) -> np.ndarray:
    """NaN cells take the value of the nearest valid cell."""
    missing = ~np.isfinite(data)
    if not missing.any():
        return data.astype(np.float64)
    idx = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
    return data[tuple(idx)].astype(np.float64)


def _auto_window(surface: np.ndarray, cell: float, units: Units) -> tuple[float, str]:
    """Largest opening window (CRS units) from the widest raised object in the data.

    A 60 m opening marks cells more than 2.5 m above its result as raised objects;
    the opening must exceed the largest object's inscribed diameter to remove it.
    """
    big = units.length(60.0)
    k = max(3, 2 * int(round(big / cell / 2)) + 1)
    kernel = np.ones((k, k), np.uint8)
    opened = cv2.morphologyEx(surface.astype(np.float32), cv2.MORPH_OPEN, kernel)
    raised = (surface - opened) > units.height(2.5)
    radius = float(ndimage.distance_transform_edt(raised).max()) * cell if raised.any() else 0.0
    width_m = 2.0 * radius * units.horizontal
    window_m = float(np.clip(width_m * 1.2 + 2.0, 10.0, 60.0))
    return units.length(window_m), f"widest raised object {width_m:.1f} m across (bounded to 10-60 m)"


def _auto_slope(surface: np.ndarray, cell: float, window: float, units: Units) -> tuple[float, str]:
    """Terrain slope tolerance: the 90th percentile gradient of the opened surface."""
    k = max(3, 2 * int(round(window / cell / 2)) + 1)
    opened = cv2.morphologyEx(surface.astype(np.float32), cv2.MORPH_OPEN, np.ones((k, k), np.uint8))
    smooth = ndimage.uniform_filter(opened.astype(np.float64), size=k, mode="nearest")
    gy, gx = np.gradient(smooth, cell)
    g = np.hypot(gx, gy) * units.vertical / units.horizontal
    p90 = float(np.percentile(g, 90))
    slope = float(np.clip(p90 * 1.5, 0.15, 1.0))
    return slope, f"90th percentile terrain gradient {p90:.3f} x 1.5, bounded to 0.15-1.0"


def _progressive_opening(surface: np.ndarray, cell: float, window: float, slope: float) -> np.ndarray:
    """Cells flagged as objects by openings with square windows of growing radius."""
    objects = np.zeros(surface.shape, bool)
    current = surface.astype(np.float32)
    radii = range(1, max(1, int(math.ceil(window / cell / 2))) + 1)
    for r in radii:
        kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        opened = cv2.morphologyEx(current, cv2.MORPH_OPEN, kernel)
        objects |= (current - opened) > slope * r * cell
        current = opened
    return objects
