"""The ASPRS class of every point of recon3d's cloud: ground, vegetation, building, other."""

from __future__ import annotations

import cv2
import numpy as np
import shapely
from scipy import ndimage

from recon3d.config import BuildingsConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster

__all__ = ["footprint_depth", "outline_labels", "point_classes"]


def point_classes(
    cloud: PointCloud,
    is_ground: np.ndarray,
    labels: np.ndarray,
    grid: Raster,
    dtm: Raster,
    config: BuildingsConfig,
    units: Units,
    *,
    vegetation: np.ndarray | None = None,
    with_solid: np.ndarray | None = None,
    roof_surface: np.ndarray | None = None,
    roughness: np.ndarray | None = None,
    tolerance: float = 0.0,
    plane_tolerance: float | None = None,
    depth: np.ndarray | None = None,
    outlines: tuple[np.ndarray, list] | None = None,
) -> np.ndarray:
    """(n,) uint8 ASPRS classes of recon3d's cloud: 2 ground, 5 vegetation, 6 building, 1 other.

    A point is building when it lies in a footprint cell (``labels`` > 0, and the
    footprint has a solid when ``with_solid`` is given), is not ground nor vegetation,
    and stands at least ``min_height / 2`` above the terrain. Vegetation wins over
    building: a crown over a roof stays a tree. With the model's roof surface under
    each point (``roof_surface``), a point more than ``tolerance`` above it is no
    building either, whatever the vegetation test said: a crown overhanging the roof,
    a tree in a courtyard. Such a point off any local plane (``roughness`` above
    ``plane_tolerance``) is vegetation (5), else other (1: an antenna, a chimney the
    model leaves out). A point more than ``tolerance`` below the roof and off any local
    plane is a crown against a wall (walls are planes): vegetation too.

    Parameters
    ----------
    cloud : PointCloud
    is_ground : (n,) bool
    labels : (rows, cols) int
        1 + footprint index per cell (:func:`label_footprints`).
    grid, dtm : Raster
        The grid of ``labels`` and the terrain.
    config : BuildingsConfig
    units : Units
    vegetation : (n,) bool, optional
    with_solid : (m + 1,) bool, optional
        Per label value (index 0 = background) whether that footprint counts.
    roof_surface : (n,) float, optional
        Height of the model's roof above each point's (x, y); NaN where no roof was
        modelled (the rule is then not applied).
    roughness : (n,) float, optional
        Per-point RMS about the local plane (NaN: not measured).
    tolerance : float
        How far above the roof surface a roof point may lie (CRS height units): a few
        times the noise of the roof points.
    plane_tolerance : float, optional
        RMS about the local plane up to which a point lies on a plane (default
        ``tolerance``).
    depth : (rows, cols) float, optional
        :func:`footprint_depth` of ``labels``, when ``labels`` is a window of a larger
        grid (a footprint may reach beyond the window).
    outlines : (label values (k,) int, k polygons), optional
        The footprints near ``grid``: the points near an outline take their footprint
        from the polygons, not from the cells (:func:`outline_labels`).
    """
    xyz = cloud.xyz
    classes = np.full(len(cloud), ASPRS.UNCLASSIFIED, np.uint8)
    row, col = grid.rowcol(xyz[:, 0], xyz[:, 1])
    rows, cols = grid.shape
    ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    lab = np.zeros(len(cloud), np.int64)
    lab[ok] = labels[row[ok], col[ok]]
    if outlines is not None:
        lab = outline_labels(xyz, lab, labels, grid, outlines)
    in_building = lab > 0 if with_solid is None else np.asarray(with_solid, bool)[lab]
    above = xyz[:, 2] - dtm.sample(xyz[:, 0], xyz[:, 1], bilinear=False)
    building = in_building & ~is_ground & (np.nan_to_num(above, nan=-np.inf) >= units.height(config.min_height / 2))
    if vegetation is not None:
        vegetation = np.asarray(vegetation, bool) & ~is_ground
    if roof_surface is not None:
        # how far inside its footprint each point lies: walls stand on the outline
        inside = footprint_depth(labels, grid.resolution) if depth is None else depth
        point_depth = np.zeros(len(cloud))
        point_depth[ok] = inside[row[ok], col[ok]]
        off_roof, crown = _off_roof(
            xyz[:, 2], np.asarray(roof_surface, np.float64), roughness, point_depth, tolerance,
            tolerance if plane_tolerance is None else plane_tolerance, units.length(1.0),
        )
        building &= ~off_roof
        crown &= building | off_roof
        vegetation = crown if vegetation is None else vegetation | crown
    if vegetation is not None:
        building &= ~vegetation
        classes[vegetation] = ASPRS.HIGH_VEGETATION
    classes[building] = ASPRS.BUILDING
    classes[is_ground] = ASPRS.GROUND
    return classes


def outline_labels(xyz: np.ndarray, lab: np.ndarray, labels: np.ndarray, grid: Raster,
                   outlines: tuple[np.ndarray, list]) -> np.ndarray:
    """Each point's footprint label, from the polygons wherever a cell's answer may be wrong.

    A cell holds one label, taken at its centre, so the points of a cell an outline
    crosses all get the centre's answer: the eave half a cell outside the footprint
    is lost, a street point half a cell inside it is taken. The points of every cell
    next to a change of label are judged against the polygons themselves (a point on
    two outlines goes to the lower label), so cloud.laz's building points are those
    inside the published footprints.

    Parameters
    ----------
    xyz : (n, 3) float
    lab : (n,) int
        Each point's cell label (0 outside every footprint and off the grid).
    labels : (rows, cols) int
        The footprint labels on ``grid``.
    grid : Raster
    outlines : ((k,) int, list of k Polygon)
        Label value and footprint of every building that may hold the points.

    Returns
    -------
    (n,) int64
    """
    values, polygons = outlines
    if not len(polygons):
        return lab
    edge = ndimage.maximum_filter(labels, size=3) != ndimage.minimum_filter(labels, size=3)
    row, col = grid.rowcol(xyz[:, 0], xyz[:, 1])
    rows, cols = labels.shape
    ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    near = np.flatnonzero(ok)[edge[row[ok], col[ok]]]
    if not len(near):
        return lab
    points = shapely.points(xyz[near, :2])
    tree = shapely.STRtree(polygons)
    hit, poly = tree.query(points, predicate="intersects")
    out = lab.copy()
    out[near] = 0
    if not len(hit):
        return out
    label = np.asarray(values, np.int64)[poly]
    first = np.lexsort((label, hit))
    keep = np.r_[True, hit[first][1:] != hit[first][:-1]]
    out[near[hit[first][keep]]] = label[first][keep]
    return out


def footprint_depth(labels: np.ndarray, cell: float) -> np.ndarray:
    """(rows, cols) float32 distance (CRS units) of each footprint cell from its outline, 0 outside.

    OpenCV's exact Euclidean transform: scipy's to float32 rounding, in a sixth of its
    working memory (its feature transform holds two int32 grids beside the float64
    result: 130 MB for a 4 M-cell survey in the coordinator).
    """
    inside = np.pad(labels > 0, 1).astype(np.uint8)  # the grid's edge is an outline too
    return cv2.distanceTransform(inside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1] * np.float32(cell)


def _off_roof(
    z: np.ndarray,
    roof: np.ndarray,
    roughness: np.ndarray | None,
    depth: np.ndarray,
    tolerance: float,
    plane_tolerance: float,
    wall_distance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Points of a footprint that are not on its roof, and those of them that are crowns.

    Parameters
    ----------
    z, roof : (n,) float
        Point heights and the roof surface above each (NaN: no roof modelled).
    roughness : (n,) float or None
    depth : (n,) float
        Distance of each point's cell from the footprint's outline (CRS units).
    tolerance, plane_tolerance, wall_distance : float

    Returns
    -------
    off_roof : (n,) bool
        More than ``tolerance`` above the roof; or more than ``tolerance`` below it and
        either off any local plane or farther than ``wall_distance`` inside the
        outline (a roof hides what lies below it: only walls are seen there).
    crown : (n,) bool
        The off-roof points that are off any local plane (all of those above the roof
        without ``roughness``).
    """
    over = z > np.nan_to_num(roof, nan=np.inf) + tolerance
    if roughness is None:
        return over, over.copy()
    off_plane = np.nan_to_num(roughness, nan=0.0) > plane_tolerance
    under = (z < np.nan_to_num(roof, nan=-np.inf) - tolerance) & (off_plane | (depth > wall_distance))
    off_roof = over | under
    return off_roof, off_roof & (off_plane | under)
