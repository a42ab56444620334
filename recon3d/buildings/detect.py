"""Building candidates: blobs of the nDSM, or footprints given by the user.

Detection follows the classic photogrammetric capture rules: a building is a
connected region of cells at least ``min_height`` above the terrain covering at least
``min_area``. Cells whose points are mostly multi-return echoes are treated as
vegetation (laser pulses pass through leaves, not roofs) and never seed a building.
"""

from __future__ import annotations

import logging

import numpy as np
import rasterio.features
import shapely
from scipy import ndimage

from recon3d.config import BuildingsConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import PointCloud
from recon3d.core.raster import Raster
from recon3d.terrain.dsm import grid_points

log = logging.getLogger(__name__)

__all__ = ["building_mask", "detect_buildings", "label_footprints", "vegetation_cells"]


def vegetation_cells(cloud: PointCloud, grid: Raster) -> np.ndarray:
    """(rows, cols) bool: cells where most points belong to multi-return pulses.

    Returns all False when the cloud has no return information (stereo clouds).
    """
    a = cloud.attributes
    if "number_of_returns" not in a:
        return np.zeros(grid.shape, bool)
    multi = (np.asarray(a["number_of_returns"]) > 1).astype(np.float64)
    xyz = np.column_stack([cloud.xyz[:, :2], multi])
    share = grid_points(xyz, grid.transform, grid.shape, reducer="mean")
    return np.nan_to_num(share) > 0.5


def building_mask(ndsm: Raster, vegetation: np.ndarray, config: BuildingsConfig, units: Units) -> np.ndarray:
    """(rows, cols) bool: raised, non-vegetation cells after a small opening.

    The opening (3 x 3 cells) removes walls' fringes, wires and one-cell spikes, and
    cuts thin bridges between neighbouring blobs.
    """
    raised = np.nan_to_num(ndsm.data) >= units.height(config.min_height)
    mask = raised & ~vegetation
    mask = ndimage.binary_opening(mask, structure=np.ones((3, 3), bool))
    return ndimage.binary_fill_holes(mask) & raised | mask


def detect_buildings(
    ndsm: Raster, vegetation: np.ndarray, config: BuildingsConfig, units: Units
) -> list[shapely.Polygon]:
    """Footprint polygons of building blobs, largest first.

    Outlines follow cell edges, are simplified by Douglas-Peucker with a tolerance of
    one cell, and blobs smaller than ``min_area`` are dropped.
    """
    mask = building_mask(ndsm, vegetation, config, units)
    labels, n = ndimage.label(mask)
    if n == 0:
        return []
    min_area = units.area(config.min_area)
    polygons = []
    for geom, value in rasterio.features.shapes(labels.astype(np.int32), mask=mask, transform=ndsm.transform):
        poly = shapely.geometry.shape(geom)
        if poly.area < min_area:
            continue
        # holes smaller than a building are gaps in the data (chimneys, dark roof
        # patches), not courtyards
        poly = shapely.Polygon(poly.exterior, [r for r in poly.interiors if shapely.Polygon(r).area >= min_area])
        poly = shapely.make_valid(poly.simplify(ndsm.resolution, preserve_topology=True))
        poly = max(getattr(poly, "geoms", [poly]), key=lambda g: g.area)
        if poly.geom_type == "Polygon" and poly.area >= min_area:
            polygons.append(shapely.orient_polygons(poly))
    polygons.sort(key=lambda p: (-p.area, p.centroid.x, p.centroid.y))
    log.info("detected %d building blobs of %d raised regions", len(polygons), n)
    return polygons


def label_footprints(polygons: list[shapely.Polygon], grid: Raster, *, all_touched: bool = False) -> np.ndarray:
    """(rows, cols) int32 image: 1 + index of the footprint covering each cell, 0 elsewhere."""
    if not polygons:
        return np.zeros(grid.shape, np.int32)
    shapes = ((p, i + 1) for i, p in enumerate(polygons))
    return rasterio.features.rasterize(
        shapes, out_shape=grid.shape, transform=grid.transform, fill=0, dtype="int32", all_touched=all_touched
    )
