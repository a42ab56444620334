"""The digital terrain model (DTM) from ground points, and the normalised DSM."""

from __future__ import annotations

import logging

import numpy as np
from scipy import interpolate, ndimage
from scipy.spatial import QhullError
from threadpoolctl import threadpool_limits

from recon3d.core.raster import Raster
from recon3d.errors import InputError
from recon3d.terrain.dsm import grid_points

log = logging.getLogger(__name__)

__all__ = ["densify_lines", "fill_gaps", "fill_nearest", "make_dtm", "make_ndsm"]


def fill_gaps(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill the unknown cells of a grid by linear interpolation in a Delaunay triangulation.

    Only the known cells on the rim of a gap are triangulated, which gives inside each
    gap the same planes as a triangulation of every known cell, at a fraction of the
    cost. Cells outside the rims' convex hull take the value of the nearest known cell.

    Parameters
    ----------
    values : (rows, cols) float
        Valid wherever ``known`` is True.
    known : (rows, cols) bool

    Returns
    -------
    (rows, cols) float64
    """
    out = np.where(known, values, np.nan).astype(np.float64)
    gaps = ~known
    if not gaps.any() or not known.any():
        return out if known.any() else np.full(values.shape, np.nan)
    out, gaps = _fill_small_gaps(out, gaps)
    if not gaps.any():
        return out
    rim = known & ndimage.binary_dilation(gaps)  # 4-connected rim: fewer vertices, same planes
    r, c = np.nonzero(rim)
    gr, gc = np.nonzero(gaps)
    try:
        # scipy locates points with one small LAPACK call per triangle; multithreaded
        # BLAS turns that into minutes of thread contention when two processes run
        with threadpool_limits(1, user_api="blas"):
            interp = interpolate.LinearNDInterpolator(np.column_stack([r, c]), out[r, c])
            out[gr, gc] = interp(np.column_stack([gr, gc]))
    except QhullError:  # rim cells all on one line: nothing to triangulate
        pass
    return fill_nearest(out)


def fill_nearest(data: np.ndarray) -> np.ndarray:
    """(rows, cols) float64 copy in which NaN cells take the value of the nearest valid cell."""
    missing = ~np.isfinite(data)
    if not missing.any():
        return data.astype(np.float64)
    idx = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
    return data[tuple(idx)].astype(np.float64)


def _fill_small_gaps(out: np.ndarray, gaps: np.ndarray, max_cells: int = 4):
    """Fill gaps of at most ``max_cells`` cells with the mean of their known 3 x 3 neighbours.

    Every cell of such a gap touches known cells, and for gaps this small the
    neighbourhood mean equals linear interpolation to within the data's noise; it
    spares the triangulation the many one-cell gaps of a sparse ground.
    """
    labels, n = ndimage.label(gaps)
    small = (np.bincount(labels.ravel()) <= max_cells)[labels] & gaps
    if not small.any():
        return out, gaps
    known = (~gaps).astype(np.float64)
    kernel = np.ones((3, 3))
    total = ndimage.convolve(np.where(gaps, 0.0, out), kernel, mode="constant")
    count = ndimage.convolve(known, kernel, mode="constant")
    out = out.copy()
    out[small] = total[small] / count[small]
    return out, gaps & ~small


def densify_lines(lines: list[np.ndarray], step: float) -> np.ndarray:
    """Points every ``step`` (or closer) along 3-D polylines, heights linear along each segment.

    Parameters
    ----------
    lines : list of (k, 3) float
    step : float

    Returns
    -------
    (m, 3) float
    """
    out = []
    for line in lines:
        a, b = line[:-1], line[1:]
        length = np.hypot(*(b - a)[:, :2].T)
        counts = np.maximum(np.ceil(length / step).astype(np.int64), 1)
        seg = np.repeat(np.arange(len(a)), counts)
        t = (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)) / counts[seg]
        out += [a[seg] + (b[seg] - a[seg]) * t[:, None], line[-1:]]
    return np.concatenate(out) if out else np.zeros((0, 3))


def make_dtm(
    ground_xyz: np.ndarray, grid: Raster, *, noise: float = 0.0, constraints: np.ndarray | None = None
) -> Raster:
    """Interpolate ground points on the grid of ``grid``.

    The ground points are averaged per cell, which removes measurement noise and
    bounds the work by the grid size; cells without ground (under buildings, water)
    are interpolated linearly in the Delaunay triangulation of the surrounding ground
    cells (:func:`fill_gaps`).

    Parameters
    ----------
    ground_xyz : (n, 3) float
    grid : Raster
        Any raster on the target grid (the DSM); only its transform and CRS are used.
    noise : float
        Height noise of the points (CRS units), as measured by the ground filter;
        noisy clouds (stereo) are averaged over a wider window (see ``_smooth_noise``).
    constraints : (m, 3) float, optional
        Heights the surface must honour: breakline vertices (densified with
        :func:`densify_lines`) and spot heights. Each cell they fall in takes their
        mean height instead of the ground points', and the interpolation of the gaps
        around them uses them as vertices, as in photogrammetric DTM production.

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
    mean = grid_points(ground_xyz, grid.transform, grid.shape, reducer="mean")
    known = np.isfinite(mean)
    if noise > 0:
        mean = _smooth_noise(mean, known, grid_points(ground_xyz, grid.transform, grid.shape, reducer="count"), noise)
    if constraints is not None and len(constraints):
        fixed = grid_points(constraints, grid.transform, grid.shape, reducer="mean")
        has = np.isfinite(fixed)
        mean[has], known = fixed[has], known | has
    dtm = fill_gaps(mean, known)
    return grid.like(dtm, product="DTM", method="per-cell mean of ground points, gaps by Delaunay interpolation")


#: Height noise (CRS units, metres for metric CRSs) a DTM cell is averaged down to.
NOISE_TARGET = 0.05


def _smooth_noise(mean: np.ndarray, known: np.ndarray, count: np.ndarray, noise: float) -> np.ndarray:
    """Average per-cell means over a window that brings the noise down to 5 cm.

    A mean of m points with noise s has noise s / sqrt(m); a square window of w cells
    holding n points each needs w^2 n >= (s / 0.05)^2. A 0.3 m stereo noise with one
    point per cell gives w = 6; LiDAR (a few cm, several points per cell) gives w = 1.
    """
    n = float(np.median(count[known])) if known.any() else 1.0
    width = int(np.ceil(np.sqrt((noise / NOISE_TARGET) ** 2 / max(n, 1.0))))
    if width <= 1:
        return mean
    weights = np.where(known, count, 0.0)
    num = ndimage.uniform_filter(np.where(known, mean, 0.0) * weights, width, mode="nearest")
    den = ndimage.uniform_filter(weights, width, mode="nearest")
    out = mean.copy()
    out[known] = num[known] / den[known]
    return out


def make_ndsm(dsm: Raster, dtm: Raster) -> Raster:
    """Height above ground, DSM minus DTM, negative values clipped to 0; NaN where the DSM is."""
    if dsm.transform != dtm.transform or dsm.shape != dtm.shape:
        raise ValueError("DSM and DTM must share one grid")
    ndsm = np.maximum(dsm.data - dtm.data, 0.0)
    return dsm.like(ndsm, product="nDSM", method="DSM - DTM, clipped at 0")
