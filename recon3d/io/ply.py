"""PLY point clouds through Open3D."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyproj

from recon3d.core.pointcloud import PointCloud
from recon3d.errors import CRSError, InputError
from recon3d.io import require_file

__all__ = ["read_ply"]


def read_ply(path: str | Path, *, crs: pyproj.CRS | None = None) -> PointCloud:
    """Read a PLY point cloud; PLY carries no CRS, so ``crs`` is required.

    Colours become ``red``, ``green``, ``blue`` (uint16, LAS scale 0..65535).
    """
    from recon3d.core.o3d import open3d

    o3d = open3d()
    path = require_file(path, "point cloud")
    if crs is None:
        raise CRSError(f"{path}: PLY files carry no CRS; give one with --crs")
    pcd = o3d.io.read_point_cloud(str(path), format="ply")
    xyz = np.asarray(pcd.points, dtype=np.float64)
    if len(xyz) == 0:
        raise InputError(f"{path}: no points could be read (empty or not a PLY point cloud)")
    if not np.isfinite(xyz).all():
        raise InputError(f"{path}: some points have NaN or infinite coordinates")
    attributes = {}
    if pcd.has_colors():
        rgb = np.round(np.asarray(pcd.colors) * 65535).astype(np.uint16)
        attributes = {"red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    return PointCloud(xyz, attributes, crs)
