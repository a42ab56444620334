"""Building footprints measured against reference outlines or a provider's classes.

Two kinds of reference are supported:

* reference outlines (a building database such as BD Uni): area-based and object-based
  completeness, correctness and quality in the ISPRS benchmark sense, and the planimetric
  RMS of the outlines;
* a provider's point classes (class 6 building): area-based scores on a fine grid whose
  cells take the class of the nearest first-return point, so that the reference is an
  area (the roofs seen from above), not a point count biased by walls and multiple echoes.

All areas and distances are in CRS units unless ``units`` is given, then in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import rasterio.features
import shapely
from affine import Affine
from scipy.spatial import cKDTree

from recon3d.buildings.vegetation import vegetation_index
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud, column_bounds

__all__ = [
    "ReferenceGrid",
    "covered_shares",
    "evaluate_against_classes",
    "evaluate_footprints",
    "nearest_point",
    "score_against_reference",
    "surface_points",
    "vegetation_as_building",
    "vegetation_counts",
    "vegetation_truth_proxy",
]


def _scores(tp: float, fp: float, fn: float) -> tuple[float | None, float | None, float | None]:
    """Completeness, correctness and quality in percent (None when undefined)."""

    def pct(a: float, b: float) -> float | None:
        return round(100.0 * a / b, 2) if b > 0 else None

    return pct(tp, tp + fn), pct(tp, tp + fp), pct(tp, tp + fp + fn)


def _polygons(geoms) -> list[shapely.Polygon]:
    """Valid polygons with an area (multipolygons split, invalid ones repaired)."""
    out = []
    for g in geoms:
        if g is None or g.is_empty:
            continue
        g = shapely.make_valid(g) if not g.is_valid else g
        out += [p for p in getattr(g, "geoms", [g]) if p.geom_type == "Polygon" and p.area > 0]
        if g.geom_type == "GeometryCollection":
            out += [q for p in g.geoms if p.geom_type == "MultiPolygon" for q in p.geoms]
    return out


def evaluate_footprints(
    detected: list[shapely.Polygon],
    reference: list[shapely.Polygon],
    *,
    overlap: float = 0.5,
    step: float | None = None,
    max_distance: float | None = None,
    units: Units | None = None,
) -> dict:
    """Detected footprints against reference footprints.

    Parameters
    ----------
    detected, reference : list of shapely.Polygon
        In one CRS. Invalid polygons are repaired, multipolygons split.
    overlap : float
        Share of an object's area that must be covered by the other set for the object
        to count as found (reference) or correct (detected); 0.5 in the ISPRS benchmark.
    step : float, optional
        Spacing of the samples along the reference outlines (CRS units); 0.5 m by default.
    max_distance : float, optional
        Outline samples farther than this from any detected outline are left out of the
        RMS and counted in ``outline_far_percent`` (an edge the detection does not have,
        e.g. a party wall between two reference buildings detected as one); 3 m by default.
    units : Units, optional
        Metres per CRS unit; areas and distances are then reported in metres.

    Returns
    -------
    dict
        ``area_completeness``, ``area_correctness``, ``area_quality`` (percent),
        ``reference_area``, ``detected_area``, ``overlap_area``;
        ``object_completeness``, ``object_correctness``, ``object_quality`` (percent),
        ``n_reference``, ``n_detected``, ``n_found`` (reference objects found),
        ``n_correct`` (detected objects on a reference); ``outline_rms``,
        ``outline_mean``, ``outline_max``, ``outline_samples``, ``outline_far_percent``
        over the found reference objects.
    """
    u = units or Units()
    det, ref = _polygons(detected), _polygons(reference)
    det_union = shapely.union_all(det) if det else shapely.Polygon()
    ref_union = shapely.union_all(ref) if ref else shapely.Polygon()
    tp = det_union.intersection(ref_union).area
    a_det, a_ref = det_union.area, ref_union.area
    comp, corr, qual = _scores(tp, a_det - tp, a_ref - tp)
    m2 = u.horizontal**2
    out: dict = {
        "area_completeness": comp,
        "area_correctness": corr,
        "area_quality": qual,
        "reference_area": round(a_ref * m2, 2),
        "detected_area": round(a_det * m2, 2),
        "overlap_area": round(tp * m2, 2),
    }
    out.update(_object_scores(det, ref, u, overlap, step, max_distance))
    return out


def _object_scores(det: list[shapely.Polygon], ref: list[shapely.Polygon], u: Units, overlap: float = 0.5,
                   step: float | None = None, max_distance: float | None = None) -> dict:
    """The ``object_*``, ``n_*`` and ``outline_*`` scores of :func:`evaluate_footprints` (its defaults)."""
    step = step if step is not None else u.length(0.5)
    max_distance = max_distance if max_distance is not None else u.length(3.0)
    ref_share, det_share = covered_shares(ref, det), covered_shares(det, ref)
    found = ref_share >= overlap
    correct = det_share >= overlap
    n_found, n_correct = int(found.sum()), int(correct.sum())
    o_comp = round(100.0 * n_found / len(ref), 2) if ref else None
    o_corr = round(100.0 * n_correct / len(det), 2) if det else None
    denom = n_found + (len(ref) - n_found) + (len(det) - n_correct)
    out = dict(
        object_completeness=o_comp,
        object_correctness=o_corr,
        object_quality=round(100.0 * n_found / denom, 2) if denom else None,
        n_reference=len(ref),
        n_detected=len(det),
        n_found=n_found,
        n_correct=n_correct,
    )
    out.update(_outline_errors([p for p, f in zip(ref, found, strict=True) if f], det, step, max_distance, u))
    return out


def covered_shares(polys: list[shapely.Polygon], others: list[shapely.Polygon]) -> np.ndarray:
    """(n,) share of each polygon's area inside the union of ``others``.

    Each polygon meets the union of the few ``others`` it touches, not the union of all:
    intersecting every polygon with a whole city's union took time quadratic in its size.
    The polygons that touch one other (most) are intersected in one vectorised call.
    """
    out = np.zeros(len(polys))
    if not polys or not others:
        return out
    polys_a, others_a = np.asarray(polys, dtype=object), np.asarray(others, dtype=object)
    which, near = shapely.STRtree(others_a).query(polys_a, predicate="intersects")
    order = np.lexsort((near, which))  # by polygon, then by the others' order
    which, near = which[order], near[order]
    counts = np.bincount(which, minlength=len(polys))
    one = counts[which] == 1
    first = which[one]
    out[first] = shapely.area(shapely.intersection(polys_a[first], others_a[near[one]])) / shapely.area(polys_a[first])
    starts = np.searchsorted(which, np.flatnonzero(counts > 1))
    for i, start in zip(np.flatnonzero(counts > 1), starts, strict=True):
        cover = shapely.union_all(others_a[near[start:start + counts[i]]])
        out[i] = polys_a[i].intersection(cover).area / polys_a[i].area
    return out


def _outline_errors(found: list[shapely.Polygon], det: list[shapely.Polygon], step, max_distance, u: Units) -> dict:
    """Distances from densified reference outlines to the nearest detected outline."""
    none = {"outline_rms": None, "outline_mean": None, "outline_max": None, "outline_samples": 0, "outline_far_percent": None}
    if not found or not det:
        return none
    tree = shapely.STRtree(det)
    dists = []
    for poly in found:
        rings = [poly.exterior, *poly.interiors]
        pts = np.concatenate([np.asarray(shapely.segmentize(r, step).coords)[:-1] for r in rings])
        near = tree.query(poly, predicate="intersects")
        if not len(near):
            continue
        edges = shapely.union_all([det[i].boundary for i in near])
        dists.append(shapely.distance(shapely.points(pts), edges))
    if not dists:
        return none
    d = np.concatenate(dists)
    close = d <= max_distance
    dc = d[close] * u.horizontal
    return {
        "outline_rms": round(float(np.sqrt(np.mean(dc**2))), 3) if close.any() else None,
        "outline_mean": round(float(dc.mean()), 3) if close.any() else None,
        "outline_max": round(float(dc.max()), 3) if close.any() else None,
        "outline_samples": int(close.sum()),
        "outline_far_percent": round(100.0 * float(np.mean(~close)), 2),
    }


def surface_points(cloud: PointCloud) -> np.ndarray:
    """Indices of the points that see the surface from above (first returns, no noise)."""
    keep = np.ones(len(cloud), bool)
    a = cloud.attributes
    if "return_number" in a:
        keep &= np.asarray(a["return_number"]) <= 1
    c = cloud.classification
    if c is not None:
        keep &= c != ASPRS.NOISE
    return np.flatnonzero(keep)


def evaluate_against_classes(
    polygons: list[shapely.Polygon],
    cloud: PointCloud,
    reference_classes: np.ndarray,
    *,
    cell: float | None = None,
    max_distance: float | None = None,
    building_class: int = ASPRS.BUILDING,
    point_classes: np.ndarray | None = None,
    vegetation_truth: np.ndarray | None = None,
    min_object_area: float | None = None,
    units: Units | None = None,
) -> dict:
    """Footprints against the provider's building class, area-based.

    The cloud's extent is cut into square cells of size ``cell``; each cell takes the
    class of the nearest first-return point (a Voronoi partition of the surface seen
    from above), cells farther than ``max_distance`` from any point are left out. A
    reference building cell has the provider's ``building_class``; a detected one has
    its centre inside a footprint.

    Parameters
    ----------
    polygons : list of shapely.Polygon
        Detected footprints, in the cloud's CRS.
    cloud : PointCloud
    reference_classes : (n,) int
        Provider classes of the cloud's points.
    cell : float, optional
        Evaluation cell (CRS units); 0.25 m by default.
    max_distance : float, optional
        Largest distance from a cell centre to its point (CRS units); 1 m by default.
    building_class : int
    point_classes : (n,) int, optional
        recon3d's own point classes (cloud.laz); with them the share of vegetation
        points labelled building is reported.
    vegetation_truth : (n,) bool, optional
        Which points are vegetation; the provider's classes 3, 4, 5 by default (see
        :func:`vegetation_truth_proxy` for providers without a vegetation class).
    min_object_area : float, optional
        Connected regions of reference building cells at least this large (CRS units
        squared; 10 m2 by default) are the reference objects of the object-based scores
        and of the outline RMS.
    units : Units, optional

    Returns
    -------
    dict
        ``completeness``, ``correctness``, ``quality`` (percent), ``reference_area``,
        ``detected_area``, ``overlap_area``, ``cell``; the object-based and outline keys
        of :func:`evaluate_footprints` (``object_completeness``..., ``outline_rms``...)
        against the reference objects; with ``point_classes`` also
        ``vegetation_points`` and ``vegetation_as_building_percent``.
    """
    u = units or Units()
    cell = cell if cell is not None else u.length(0.25)
    max_distance = max_distance if max_distance is not None else u.length(1.0)
    reference_classes = np.asarray(reference_classes)
    idx = surface_points(cloud)
    if not len(idx):
        raise ValueError("evaluate_against_classes: the cloud has no surface point")
    xy = cloud.xyz[idx, :2]
    grid = ReferenceGrid.over(*column_bounds(xy), cell)
    gx, gy = grid.centres()
    valid, nearest = nearest_point(xy, np.column_stack([gx.ravel(), gy.ravel()]), max_distance)
    ref = np.zeros(valid.shape, bool)
    ref[valid] = reference_classes[idx[nearest[valid]]] == building_class
    out = score_against_reference(polygons, grid, ref.reshape(grid.shape), valid.reshape(grid.shape),
                                  min_object_area=min_object_area, units=u)
    if point_classes is not None:
        if vegetation_truth is None:
            vegetation_truth = np.isin(reference_classes, (3, 4, 5))
        out.update(vegetation_as_building(*vegetation_counts(vegetation_truth, point_classes)))
    return out


@dataclass(frozen=True)
class ReferenceGrid:
    """The grid of :func:`evaluate_against_classes`: square cells from the lowest corner
    of the surface points, over their extent."""

    transform: Affine
    shape: tuple[int, int]

    @classmethod
    def over(cls, lo, hi, cell: float) -> ReferenceGrid:
        cols = max(1, int(np.ceil((hi[0] - lo[0]) / cell)))
        rows = max(1, int(np.ceil((hi[1] - lo[1]) / cell)))
        return cls(Affine(cell, 0.0, lo[0], 0.0, -cell, lo[1] + rows * cell), (rows, cols))

    def centres(self, rows: slice = slice(None), cols: slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """(r, c) x and y of the centres of ``[rows, cols]`` of the cells."""
        t, (n, m) = self.transform, self.shape
        cx = t.c + (np.arange(m)[cols] + 0.5) * t.a
        cy = t.f + (np.arange(n)[rows] + 0.5) * t.e
        return np.meshgrid(cx, cy)


def nearest_point(xy: np.ndarray, centres: np.ndarray, max_distance: float,
                  order: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The point nearest each centre, within ``max_distance``; of two as near, the first in ``order``.

    Returns
    -------
    valid : (m,) bool
    nearest : (m,) int
        Index into ``xy`` (meaningless where not valid).
    """
    valid, nearest = np.zeros(len(centres), bool), np.zeros(len(centres), np.int64)
    if not len(xy):
        return valid, nearest
    k = min(2, len(xy))
    tree = cKDTree(xy)
    rank = np.arange(len(xy)) if order is None else np.asarray(order)
    for start in range(0, len(centres), QUERY_CHUNK):  # memory of a chunk, not of the tile's cells
        part = slice(start, start + QUERY_CHUNK)
        dist, nb = tree.query(centres[part], k=k, distance_upper_bound=max_distance, workers=-1)
        dist, nb = dist.reshape(-1, k), nb.reshape(-1, k)
        near = nb[:, 0].copy()
        if k == 2:
            tie = np.isfinite(dist[:, 1]) & (dist[:, 1] == dist[:, 0])
            second = nb[tie, 1]
            swap = rank[second] < rank[near[tie]]
            near[np.flatnonzero(tie)[swap]] = second[swap]
        valid[part] = np.isfinite(dist[:, 0])
        nearest[part] = np.where(valid[part], near, 0)
    return valid, nearest


#: Centres :func:`nearest_point` looks up at a time.
QUERY_CHUNK = 1 << 18


def score_against_reference(
    polygons: list[shapely.Polygon], grid: ReferenceGrid, ref: np.ndarray, valid: np.ndarray, *,
    min_object_area: float | None = None, units: Units | None = None,
) -> dict:
    """The area and object scores of :func:`evaluate_against_classes` from its reference grid.

    Parameters
    ----------
    polygons : list of shapely.Polygon
    grid : ReferenceGrid
    ref, valid : (rows, cols) bool
        Cells whose nearest surface point is of the building class; cells with a surface
        point near enough to judge.
    """
    u = units or Units()
    min_object_area = min_object_area if min_object_area is not None else u.area(10.0)
    rows, cols = grid.shape
    cell = grid.transform.a
    polys = _polygons(polygons)
    if polys:
        det = rasterio.features.rasterize(
            ((p, 1) for p in polys), out_shape=(rows, cols), transform=grid.transform, fill=0, dtype="uint8"
        ).astype(bool)
    else:
        det = np.zeros((rows, cols), bool)
    det &= valid
    ref = ref & valid
    out_objects = _objects_from_grid(ref, grid.transform, polys, min_object_area, u)
    tp = float(np.count_nonzero(det & ref))
    fp = float(np.count_nonzero(det & ~ref))
    fn = float(np.count_nonzero(~det & ref))
    comp, corr, qual = _scores(tp, fp, fn)
    a = (cell * u.horizontal) ** 2
    out = {
        "completeness": comp,
        "correctness": corr,
        "quality": qual,
        "reference_area": round((tp + fn) * a, 2),
        "detected_area": round((tp + fp) * a, 2),
        "overlap_area": round(tp * a, 2),
        "cell": cell,
    }
    out.update(out_objects)
    return out


def vegetation_counts(vegetation_truth: np.ndarray, point_classes: np.ndarray) -> tuple[int, int]:
    """(vegetation points, those of them labelled building): summed over tiles for
    :func:`vegetation_as_building`."""
    veg = np.asarray(vegetation_truth, bool)
    return int(veg.sum()), int(np.count_nonzero(np.asarray(point_classes)[veg] == ASPRS.BUILDING))


def vegetation_as_building(vegetation: int, as_building: int) -> dict:
    """``vegetation_points`` and ``vegetation_as_building_percent`` of :func:`evaluate_against_classes`."""
    return {"vegetation_points": vegetation,
            "vegetation_as_building_percent": round(100.0 * as_building / vegetation, 3) if vegetation else None}


def _objects_from_grid(ref: np.ndarray, transform: Affine, polys: list, min_area: float, u: Units) -> dict:
    """Object-based scores and outline RMS against the connected regions of a reference mask."""
    objects = []
    if ref.any():
        for geom, _ in rasterio.features.shapes(ref.astype(np.uint8), mask=ref, transform=transform, connectivity=4):
            poly = shapely.geometry.shape(geom)
            if poly.area >= min_area:
                objects.append(poly)
    return _object_scores(polys, _polygons(objects), u)


def vegetation_truth_proxy(
    cloud: PointCloud,
    reference_classes: np.ndarray,
    height: np.ndarray,
    *,
    min_height: float,
    ndvi_min: float = 0.3,
    greenness_min: float = 0.05,
    colour: str | None = "auto",
) -> np.ndarray:
    """(n,) bool: points taken as vegetation where the provider has no vegetation class.

    A point counts as vegetation when the provider does not call it ground, building
    or water, it lies at least ``min_height`` above the terrain, belongs to a pulse with
    several returns, and, when the cloud has colours, looks green: NDVI above
    ``ndvi_min`` when the near-infrared channel holds data, else the normalised excess
    green (2G - R - B) / (R + G + B) above ``greenness_min``. Providers whose class 1
    holds trees and unclassified roofs alike (IGN LiDAR HD) need such a proxy.

    Parameters
    ----------
    cloud : PointCloud
    reference_classes : (n,) int
    height : (n,) float
        Height of each point above the terrain (CRS height units).
    min_height : float
        CRS height units.
    colour : str or None
        The survey's colour index when ``cloud`` is a tile of it
        (:func:`~recon3d.buildings.vegetation.colour_kind`); "auto" asks the cloud.
    """
    c = np.asarray(reference_classes)
    a = cloud.attributes
    veg = np.isin(c, (3, 4, 5))
    other = ~np.isin(c, (ASPRS.GROUND, ASPRS.BUILDING, ASPRS.WATER, ASPRS.NOISE))
    cand = other & (np.nan_to_num(height, nan=-np.inf) >= min_height)
    if "number_of_returns" in a:
        cand &= np.asarray(a["number_of_returns"]) > 1
    colour = vegetation_index(cloud, colour)
    if colour is not None:
        index, kind = colour
        cand &= index > (ndvi_min if kind == "ndvi" else greenness_min)
    return veg | cand
