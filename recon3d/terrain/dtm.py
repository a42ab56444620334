"""The digital terrain model (DTM) from ground points, and the normalised DSM."""

from __future__ import annotations

import logging

import numpy as np
from scipy import interpolate, ndimage
from scipy.spatial import QhullError

from recon3d.core.raster import Raster
from recon3d.errors import InputError
from recon3d.terrain.dsm import grid_points

log = logging.getLogger(__name__)

__all__ = ["make_dtm", "make_ndsm"]


def make_dtm(ground_xyz: np.ndarray, grid: Raster) -> Raster:
    """Interpolate ground points on the grid of ``grid`` by Delaunay triangulation.

    The points are first averaged per cell (one mean point per cell holding ground),
    which removes measurement noise and bounds the triangulation by the grid size, not
    by the point count. Cells under large buildings are linear across the triangles
    that span them; cells outside the ground's convex hull take the nearest value.

    Parameters
    ----------
    ground_xyz : (n, 3) float
    grid : Raster
        Any raster on the target grid (the DSM); only its transform and CRS are used.

    Raises
    ------
    InputError
        When there are fewer than three ground points.
    """
    if len(ground_xyz) < 3:
        raise InputError(
            f"only {len(ground_xyz)} ground points were found; a DTM needs at least 3 "
            "(is the input a rooftop-only crop?)"
        )
    t, shape = grid.transform, grid.shape
    means = [grid_points(ground_xyz[:, [0, 1, k]], t, shape, reducer="mean") for k in range(3)]
    has = np.isfinite(means[2])
    pts = np.column_stack([m[has] for m in means])
    x, y = grid.cell_centers()
    gx, gy = np.meshgrid(x, y)
    try:
        dtm = interpolate.LinearNDInterpolator(pts[:, :2], pts[:, 2])(gx, gy)
    except QhullError:  # all ground cells on a line: nothing to triangulate
        dtm = np.full(shape, np.nan)
    missing = ~np.isfinite(dtm)
    if missing.all():
        dtm = np.full(shape, float(np.median(pts[:, 2])))
    elif missing.any():
        idx = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
        dtm = dtm[tuple(idx)]
    return grid.like(dtm, product="DTM", method="Delaunay interpolation of per-cell mean ground points")


def make_ndsm(dsm: Raster, dtm: Raster) -> Raster:
    """Height above ground, DSM minus DTM, negative values clipped to 0; NaN where the DSM is."""
    if dsm.transform != dtm.transform or dsm.shape != dtm.shape:
        raise ValueError("DSM and DTM must share one grid")
    ndsm = np.maximum(dsm.data - dtm.data, 0.0)
    return dsm.like(ndsm, product="nDSM", method="DSM - DTM, clipped at 0")
