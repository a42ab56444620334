"""Fusing the point clouds of several stereo pairs into one, by quality."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from recon3d.core.pointcloud import PointCloud

log = logging.getLogger(__name__)

__all__ = ["fuse"]


def fuse(
    clouds: list[PointCloud],
    *,
    cell: float,
    neighbours: int = 16,
    std_ratio: float = 2.5,
    rough: Callable[[PointCloud], np.ndarray | None] | None = None,
) -> PointCloud:
    """Merge pair clouds, keep the best points where pairs overlap, remove outliers.

    Where several pairs put points in the same ``cell`` x ``cell`` column footprint
    (at half the cell), only the points of the pair with the highest mean quality
    there are kept, so a weak pair cannot blur a good one. Then Open3D's statistical
    outlier removal drops isolated points (deterministic), except the points
    ``rough`` marks: on a surface rough by nature (foliage) a sparse point is the
    outer edge of a crown, not a mismatch.

    Parameters
    ----------
    clouds : list of PointCloud
        Same attributes in each.
    cell : float
        Ground sampling distance (model units).
    neighbours, std_ratio : int, float
        Open3D ``remove_statistical_outlier`` parameters.
    rough : callable, optional
        ``rough(merged)`` -> (n,) bool of the points exempt from outlier removal, or None.
    """
    if len(clouds) > 1:
        clouds = _best_pair_per_cell(clouds, cell / 2)
    keys = clouds[0].attributes.keys()
    merged = PointCloud(
        np.concatenate([c.xyz for c in clouds]),
        {k: np.concatenate([c.attributes[k] for c in clouds]) for k in keys},
        clouds[0].crs,
    )
    if len(merged) < neighbours * 2:
        return merged
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(merged.xyz))
    _, kept = pcd.remove_statistical_outlier(nb_neighbors=neighbours, std_ratio=std_ratio)
    keep = np.zeros(len(merged), bool)
    keep[np.asarray(kept, dtype=np.int64)] = True
    exempt = rough(merged) if rough is not None else None
    if exempt is not None:
        log.info("fusion: %d outliers kept on rough surfaces", int(np.count_nonzero(exempt & ~keep)))
        keep |= exempt
    log.info("fusion: %d of %d points kept after outlier removal", int(keep.sum()), len(merged))
    return merged[np.flatnonzero(keep)]


def _best_pair_per_cell(clouds: list[PointCloud], cell: float) -> list[PointCloud]:
    lo = np.min([c.xyz[:, :2].min(axis=0) for c in clouds], axis=0)
    keys = [np.floor((c.xyz[:, :2] - lo) / cell).astype(np.int64) for c in clouds]
    ny = max(int(k[:, 1].max()) for k in keys) + 1
    flat = [k[:, 0] * ny + k[:, 1] for k in keys]
    size = max(int(f.max()) for f in flat) + 1
    means = []
    for c, f in zip(clouds, flat, strict=True):
        s = np.bincount(f, weights=c.attributes["quality"], minlength=size)
        n = np.bincount(f, minlength=size)
        with np.errstate(invalid="ignore", divide="ignore"):
            means.append(np.where(n > 0, s / n, -1.0))
    best = np.argmax(np.stack(means), axis=0)
    return [c[best[f] == i] for i, (c, f) in enumerate(zip(clouds, flat, strict=True))]
