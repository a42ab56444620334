"""Fusing the point clouds of several stereo pairs into one, by quality."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from recon3d.core.pointcloud import PointCloud, column_bounds

log = logging.getLogger(__name__)

__all__ = ["fuse", "isolated"]


def fuse(
    clouds: list[PointCloud],
    *,
    cell: float,
    min_neighbours: int = 4,
    rough: Callable[[PointCloud], np.ndarray | None] | None = None,
) -> PointCloud:
    """Merge pair clouds, keep the best points where pairs overlap, remove isolated points.

    Where several pairs put points in the same ``cell`` x ``cell`` column footprint
    (at half the cell), only the points of the pair with the highest mean quality
    there are kept, so a weak pair cannot blur a good one. Then points with fewer than
    ``min_neighbours`` others in the 3 x 3 x 3 cubes of ``cell`` around them
    (:func:`isolated`) are dropped,
    except the points ``rough`` marks: on a surface rough by nature (foliage) a sparse
    point is the outer edge of a crown, not a mismatch.

    Parameters
    ----------
    clouds : list of PointCloud
        Same attributes in each.
    cell : float
        Ground sampling distance (model units).
    min_neighbours : int
        Fewest neighbours a point keeps.
    rough : callable, optional
        ``rough(merged)`` -> (n,) bool of the points exempt from the removal, or None.
    """
    if len(clouds) > 1:
        clouds = _best_pair_per_cell(clouds, cell / 2)
    keys = clouds[0].attributes.keys()
    merged = PointCloud(
        np.concatenate([c.xyz for c in clouds]),
        {k: np.concatenate([c.attributes[k] for c in clouds]) for k in keys},
        clouds[0].crs,
    )
    if len(merged) < 2 * min_neighbours:
        return merged
    keep = ~isolated(merged.xyz, cell, min_neighbours)
    exempt = rough(merged) if rough is not None else None
    if exempt is not None:
        log.info("fusion: %d isolated points kept on rough surfaces", int(np.count_nonzero(exempt & ~keep)))
        keep |= exempt
    log.info("fusion: %d of %d points kept after outlier removal", int(keep.sum()), len(merged))
    return merged[np.flatnonzero(keep)]


def isolated(xyz: np.ndarray, voxel: float, min_neighbours: int) -> np.ndarray:
    """(n,) bool: points with fewer than ``min_neighbours`` other points in their own and
    the 26 adjacent ``voxel``-sized cubes.

    A surface sampled every ``voxel`` puts about ten points in that neighbourhood; a
    mismatch floating above or below it, a few at most. Memory and time grow with the
    number of points (a hash of voxels, no neighbour search), so a block's tens of
    millions of points are cleaned in seconds. It replaces Open3D's statistical outlier
    removal (16 neighbours, 2.5 standard deviations), which took 50 s and 11 GB for the
    10 million points of a 6-image block, for the same DSMs on the survey family (within
    0.01-0.03 m of tolerant RMS either way) and 0.04 m less bias on the demo city.
    """
    v = np.floor((xyz - column_bounds(xyz)[0]) / voxel).astype(np.int64) + 1
    dims = column_bounds(v)[1] + 2
    key = (v[:, 0] * dims[1] + v[:, 1]) * dims[2] + v[:, 2]
    cells, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    # z is the fastest index: a column's three cubes are neighbours in the sorted keys,
    # so one search per column finds all three
    padded_cells = np.r_[-2, cells, cells[-1] + 2]  # sentinels: no key is next to them
    padded_counts = np.r_[0, counts, 0]
    total = np.zeros(len(cells), np.int64)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            centre = cells + (dx * dims[1] + dy) * dims[2]
            at = np.searchsorted(padded_cells, centre)  # the first key >= centre
            for dz, index in ((-1, at - 1), (0, at), (1, at), (1, at + 1)):
                index = np.minimum(index, len(padded_cells) - 1)
                total += np.where(padded_cells[index] == centre + dz, padded_counts[index], 0)
    return (total[inverse] - 1) < min_neighbours


def _best_pair_per_cell(clouds: list[PointCloud], cell: float) -> list[PointCloud]:
    """Each cloud cut to the cells where its mean quality is the highest of all clouds'
    (ties: the first cloud). Sparse: memory grows with the points, not the extent."""
    bounds = [column_bounds(c.xyz[:, :2]) for c in clouds]
    lo = np.min([b[0] for b in bounds], axis=0)
    hi = np.max([b[1] for b in bounds], axis=0)
    ny = int(np.floor((hi[1] - lo[1]) / cell)) + 1
    flat = []
    stats = []  # per cloud: its cells, their mean quality
    for k, c in enumerate(clouds):
        ij = np.floor((c.xyz[:, :2] - lo) / cell).astype(np.int64)
        key = ij[:, 0] * ny + ij[:, 1]
        cells, inverse = np.unique(key, return_inverse=True)
        mean = np.bincount(inverse, weights=c.attributes["quality"]) / np.bincount(inverse)
        flat.append(key)
        stats.append((cells, mean, np.full(len(cells), k)))
    cells, mean, owner = (np.concatenate(v) for v in zip(*stats, strict=True))
    order = np.lexsort((owner, -mean, cells))  # by cell, best mean first, then the first cloud
    cells, owner = cells[order], owner[order]
    first = np.r_[True, cells[1:] != cells[:-1]]
    best_cells, best_owner = cells[first], owner[first]
    out = []
    for k, (c, key) in enumerate(zip(clouds, flat, strict=True)):
        at = np.searchsorted(best_cells, key)
        out.append(c[best_owner[at] == k])
    return out
