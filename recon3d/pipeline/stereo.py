"""Frame stereo: an oriented scene folder to a dense point cloud in world coordinates."""

from __future__ import annotations

import logging

import cv2
import numpy as np

from recon3d.config import StereoConfig
from recon3d.core.pointcloud import PointCloud
from recon3d.errors import InputError
from recon3d.io.colmap import StereoScene
from recon3d.stereo.fuse import fuse
from recon3d.stereo.rectify import disparity_range, rectify_pair, select_pairs
from recon3d.stereo.triangulate import triangulate

log = logging.getLogger(__name__)

__all__ = ["dense_cloud"]


def dense_cloud(scene: StereoScene, config: StereoConfig) -> tuple[PointCloud, dict]:
    """Match every usable pair of the scene and fuse the results.

    Returns
    -------
    cloud : PointCloud
        World coordinates (model + offset), the scene's CRS; colours and ``quality``.
    report : dict
        Pairs considered, rectification residuals, disparity ranges, point counts.
    """
    from recon3d.stereo.match import MatchParams, match, photo_consistency

    pairs, candidates = select_pairs(scene.cameras, scene.sparse)
    report = {"candidates": candidates, "pairs": []}
    clouds = []
    for i, j in pairs:
        a, b = scene.cameras[i], scene.cameras[j]
        pair = rectify_pair(a, b, _read(a.image_path), _read(b.image_path), max_parallax=config.max_parallax)
        dmin, dmax, why = disparity_range(pair, scene.sparse, max_count=config.max_disparities)
        # black borders outside the photos are nodata, not texture to match
        left = np.where(pair.valid_left, pair.left, np.nan).astype(np.float32)
        right = np.where(pair.valid_right, pair.right, np.nan).astype(np.float32)
        result = match(left, right, MatchParams(min_disparity=dmin, max_disparity=dmax + 1), guide=pair.color)
        # a filled-in disparity the images agree with is as good as a match (steep or
        # shadowed roof faces); one they contradict is a guess (a hidden courtyard)
        guessed = result.filled & ~(photo_consistency(left, right, result.disparity) >= 0.4)
        cloud = triangulate(pair, result.disparity, result.confidence, min_angle_deg=config.min_angle, guessed=guessed)
        source = len(clouds) + 1  # the pair's id in cloud.laz
        cloud.attributes["point_source_id"] = np.full(len(cloud), source, np.uint16)
        report["pairs"].append({
            "pair": pair.name,
            "point_source_id": source,
            "vertical_parallax_px": pair.parallax,
            "disparity_range": {"value": [dmin, dmax], "reason": why},
            "matched_percent": result.params.get("matched_percent"),
            "density_percent": round(100.0 * float(np.mean(np.isfinite(result.disparity[pair.valid_left]))), 1),
            "points": len(cloud),
        })
        clouds.append(cloud)
    clouds = [c for c in clouds if len(c)]
    if not clouds:
        raise InputError(f"{scene.folder}: dense matching produced no point")
    gsd = _ground_sample_distance(scene)
    cloud = fuse(clouds, cell=gsd, rough=_foliage)
    cloud = PointCloud(cloud.xyz + scene.offset, cloud.attributes, scene.crs)
    report["ground_sample_distance"] = round(gsd, 4)
    report["points"] = len(cloud)
    return cloud, report


def _foliage(cloud: PointCloud) -> np.ndarray | None:
    """(n,) bool: points coloured like foliage (the colour-only vegetation threshold)."""
    from recon3d.buildings.detect import COLOUR_ONLY_THRESHOLDS, vegetation_index

    index = vegetation_index(cloud)
    return None if index is None else index[0] > COLOUR_ONLY_THRESHOLDS[index[1]]


def _read(path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"{path}: unreadable image")
    return image


def _ground_sample_distance(scene: StereoScene) -> float:
    """Median pixel footprint on the ground: depth of the sparse points over the focal length."""
    cam = scene.cameras[0]
    _, depth = cam.project(scene.sparse)
    depth = depth[depth > 0]
    return float(np.median(depth) / cam.K[0, 0]) if depth.size else 1.0
