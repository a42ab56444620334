"""Building solids by level of detail.

LoD1 is the footprint extruded from the terrain to a representative roof height: a
prism with one ground surface, one roof surface and one wall per footprint edge,
courtyards included. LoD1.3 (one flat height per roof part) and LoD2.2 (roof planes,
step walls) are assembled from a planar partition of the footprint (the comments
below); :func:`build_lods` builds them with the fallback chain LoD2.2 -> LoD1.3 -> LoD1.
Solids are built in the city model's local frame so that float32 consumers (glTF, OBJ
importers) keep millimetres.

The layers, each in its module:

- :mod:`recon3d.buildings.roofgrid`: the footprint rastered into cells labelled by roof plane;
- :mod:`recon3d.buildings.partition`: the grid's regions as a planar partition of the footprint;
- :mod:`recon3d.buildings.extrude`: solids from a partition (and LoD1 prisms);
- this module: the LoD2.2 and LoD1.3 assembly, the checks and the fallback chain.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
import shapely

from recon3d.buildings.extrude import MinRootSets, clean_footprint, lod1_solid, partition_solid
from recon3d.buildings.partition import (
    absorb_small,
    arrangement,
    grid_regions,
    open_crossings,
    open_pinches,
    partition_rms,
    refit_parts,
)
from recon3d.buildings.roofgrid import LodFailure, RoofGrid, height_levels, label_grid, unpinch
from recon3d.core.city import Solid
from recon3d.core.geo import LocalFrame

log = logging.getLogger(__name__)

__all__ = [
    "LOD_REASONS",
    "LodResult",
    "build_lods",
    "clean_footprint",
    "lod13_solid",
    "lod1_solid",
    "lod22_solid",
]


# --------------------------------------------------------------------------- LoD1.3 and LoD2.2
#
# Both are built the same way, in the city model's local frame:
#
# 0. a cloud denser than MAX_ROOF_DENSITY is thinned to it (the first point in sorted
#    order of every cell of a fixed grid);
# 1. each roof point carries the label of its roof plane (``roofs.segment_roof``);
#    a raster over the footprint (1.5 point spacings, 0.25-1 m) takes, per cell, the
#    majority label of its points; empty cells take the nearest labelled cell's
#    label, a 3 x 3 majority filter removes speckle, patches under 1 m2 go to their
#    neighbours and checkerboard corners are removed;
# 2. the raster regions are polygonized; the edges two regions share are
#    straightened (Douglas-Peucker) and moved onto the line fitted through the
#    midpoints of neighbouring point pairs from either side, so a step wall lies
#    half-way between the last points of the upper roof and the first of the lower
#    one; the regions are clipped by the exact footprint;
# 3. (LoD2.2) where two neighbouring planes intersect near their common edge and the
#    points agree, the footprint is cut along the exact intersection line (ridges,
#    hips, valleys); the other edges stay height jumps. Faces of the arrangement take
#    the label of the raster region they overlap most, and a part most of whose points
#    lie more than 1 m off that plane takes the plane they lie on
#    (``partition.refit_parts``);
# 4. slivers are merged into neighbours, parts touching themselves at a vertex are
#    opened, the partition is snapped to a 2 mm grid and made conforming (every
#    vertex lying on an edge is inserted into it, edges are split where two planes
#    cross along them);
# 5. the solid is assembled directly from that planar partition: one roof polygon per
#    part at its plane's heights, a vertical wall wherever neighbouring parts differ
#    in height along their common edge (vertical edges split at every intermediate
#    height, so every edge of the shell is shared by exactly two surfaces), walls down
#    to ground_z along the outline and one ground surface; heights closer than 5 mm at
#    a vertex are made equal and coplanar neighbouring walls merged. No boolean
#    operation is involved, so nothing is lost to float32 and the surfaces are exact
#    planar polygons with holes (CityJSON style), outer rings counter-clockwise seen
#    from outside.
#
# LoD1.3 uses the same regions with one flat height per region (the 70th percentile
# of its points; neighbours closer than ``lod13_step`` merged); when planes hold less
# than half the roof points (a spire), the regions are height terraces of
# ``lod13_step`` instead. Every solid is
# validated with ``quality.meshcheck.check_solid`` before it is returned; a LoD that
# fails falls back to the next one with a reason:
#
#   degenerate_footprint  nothing with area is left of the footprint
#   too_few_points   fewer roof points than one plane needs
#   no_roof_planes   RANSAC found no plane
#   too_many_planes  more planes than ``LodConfig.max_planes``
#   low_coverage     less than half of the roof points lie on a plane
#   poor_fit         robust point-to-roof RMS above ``LodConfig.max_roof_rms``, or a
#                    plane reaching down to the ground
#   invalid_mesh     the solid failed check_solid (val3dity-style)
#   no_points / too_low   not even a LoD1 block (no roof height, roof below 0.5 m)
#   too_large        the roof's label grid would not fit in the memory available
#   internal_error   an unexpected exception (logged with its traceback)

#: Reason codes of a LoD that could not be built (see the module comments).
LOD_REASONS = (
    "degenerate_footprint",
    "too_few_points",
    "no_roof_planes",
    "too_many_planes",
    "low_coverage",
    "poor_fit",
    "invalid_mesh",
    "no_points",
    "too_low",
    "too_large",
    "internal_error",
)


#: Roof points per m2 (plan) beyond which a building's points are thinned to this density
#: on a fixed grid before its roof is modelled. Dense image matching gives 100-400, and
#: where a crown overhangs a roof it is matched at every height, so its points outnumbered
#: the roof's and the roof failed LoD2.2 for low coverage; the partition's work also grew
#: with the points. Airborne LiDAR (8-25 points/m2) is below it and unchanged.
MAX_ROOF_DENSITY = 32.0


class LodResult(NamedTuple):
    """What :func:`build_lods` made of one building.

    Attributes
    ----------
    solids : dict of str to Solid
        By LoD ("1", "1.3", "2.2"), local frame; every one passed ``check_solid``.
    roof_type : str
        One of ``roofs.ROOF_TYPES``, or "unknown" without roof planes.
    status : str
        "ok" (every requested LoD built), "fallback" (the highest requested LoD
        failed, a lower one stands in) or "failed" (no solid).
    reason : str or None
        Why the highest requested LoD failed (see :data:`LOD_REASONS`).
    roof_rms : float
        Robust RMS of the vertical point-to-roof distances of the best solid (points
        more than ``outlier`` off excluded, see ``quality.roofs.roof_rms``), in CRS
        height units; NaN without a solid.
    planes : list of RoofPlane
        The roof planes, local frame (empty when none were searched or found).
    validity : dict of str to tuple of int
        By LoD attempted: the val3dity error codes of its solid's check, ``()`` when
        it passed (every LoD in ``solids``); codes only when the check failed it.
    """

    solids: dict
    roof_type: str
    status: str
    reason: str | None
    roof_rms: float
    planes: list
    validity: dict = {}


def build_lods(
    footprint: shapely.Polygon,
    points: np.ndarray,
    ground_z: float,
    roof_z: float,
    frame: LocalFrame,
    config=None,
    *,
    units=None,
) -> LodResult:
    """Solids of one building for the LoDs of ``config.lods``, with the fallback chain.

    Parameters
    ----------
    footprint : shapely.Polygon
        Footprint in world coordinates; cleaned with :func:`clean_footprint` (1 cm)
        first, so repeated or collinear vertices do no harm.
    points : (n, 3) float
        Points of the building in world coordinates; points outside the footprint
        or less than ``min(1 m, half the building height)`` above ``ground_z`` are
        ignored, so passing the points of the footprint's bounding box is fine.
        Roof points denser than :data:`MAX_ROOF_DENSITY` are thinned to it.
    ground_z, roof_z : float
        Terrain height under the building and LoD1 roof height (world heights);
        a NaN ``roof_z`` is replaced by the 90th percentile of the roof points.
    frame : LocalFrame
        Frame of the returned solids.
    config : LodConfig, optional
        Settings in metres; by default LoDs "1", "1.3" and "2.2" with the
        :class:`~recon3d.config.LodConfig` defaults.
    units : Units, optional
        Units of the CRS (metres when omitted).

    Returns
    -------
    LodResult
        Never raises for bad geometry: a LoD that cannot be built is reported
        through ``status`` and ``reason``.
    """
    from recon3d.buildings.roofs import RoofParams, roof_type
    from recon3d.config import LodConfig
    from recon3d.core.geo import Units
    from recon3d.quality.roofs import roof_rms as _roof_rms

    cfg = config or LodConfig(lods=("1", "1.3", "2.2"))
    u = units or Units()
    lods = [lod for lod in ("1", "1.3", "2.2") if lod in cfg.lods] or ["1"]
    failed = LodResult({}, "unknown", "failed", None, float("nan"), [])
    footprint = clean_footprint(footprint, u.length(0.01)) if footprint is not None else None
    if footprint is None:
        return failed._replace(reason="degenerate_footprint")
    ox, oy, oz = frame.origin
    fp = shapely.transform(footprint, lambda c: c - np.array([ox, oy]))
    g = float(ground_z) - oz
    pts = frame.to_local(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts):
        pts = pts[shapely.contains_xy(fp, pts[:, 0], pts[:, 1])]
    r = float(roof_z) - oz if np.isfinite(roof_z) else float("nan")
    above = u.height(1.0) if not np.isfinite(r) else min(u.height(1.0), 0.5 * (r - g))
    roof_pts = pts[pts[:, 2] > g + max(above, u.height(0.2))] if np.isfinite(g) else pts[:0]
    if not np.isfinite(r) and len(roof_pts):
        r = float(np.percentile(roof_pts[:, 2], 90))
    roof_pts = _thin_dense(roof_pts, fp.area, 1.0 / u.area(1.0 / MAX_ROOF_DENSITY))
    if not np.isfinite(g) or not np.isfinite(r):
        return failed._replace(reason="no_points")
    if not r - g >= u.height(0.5):
        return failed._replace(reason="too_low")

    solids: dict[str, Solid] = {}
    reasons: dict[str, str] = {}
    codes: dict[str, tuple[int, ...]] = {}
    lod1 = lod1_solid(footprint, g + oz, r + oz, frame)
    issues = _issues(lod1, u)
    if issues:
        return failed._replace(reason="invalid_mesh", validity={"1": _codes(issues)})
    want22 = "2.2" in lods
    params = RoofParams.from_config(cfg, u)
    seg, grid = None, None
    if "1.3" in lods or want22:
        try:
            seg, grid, why = _segment(roof_pts, fp, params, u)
        except Exception:  # a bug must not cost the building its LoD1
            log.warning("roof segmentation failed", exc_info=True)
            why = "internal_error"
        if why:
            reasons["1.3"] = reasons["2.2"] = why
    rms22 = float("nan")
    if want22 and "2.2" not in reasons:
        built = _attempt("2.2", lambda: _lod22(grid, fp, seg, roof_pts, g, u, cfg), reasons, codes)
        if built is not None:
            solids["2.2"], rms22 = built
    if ("1.3" in lods or "2.2" in reasons) and "1.3" not in reasons and grid is not None:
        built = _attempt("1.3", lambda: _lod13_of(grid, fp, seg, roof_pts, g, u, cfg), reasons, codes)
        if built is not None:
            solids["1.3"] = built
    solids["1"] = lod1
    if "1" not in lods and len(solids) > 1:
        del solids["1"]
    best = max(solids, key=float)
    if best == "2.2":
        rms = rms22
    else:
        rms = float("nan")
        if len(roof_pts):
            rms = _roof_rms(solids[best], roof_pts, outlier=u.height(1.0))
    top = lods[-1]
    status = "ok" if top in solids else "fallback"
    kind = roof_type(seg) if seg is not None else "unknown"
    planes = seg.planes if seg is not None else []
    ordered = dict(sorted(solids.items(), key=lambda kv: float(kv[0])))
    validity = dict(sorted(({lod: () for lod in ordered} | codes).items(), key=lambda kv: float(kv[0])))
    return LodResult(ordered, kind, status, None if status == "ok" else reasons.get(top), rms, planes, validity)


def _thin_dense(points: np.ndarray, area: float, max_density: float) -> np.ndarray:
    """``points`` (n, 3), or when there are more than ``max_density`` per unit of
    ``area`` (the footprint's), the first point in sorted order of every cell of a fixed
    grid of that density (:func:`~recon3d.buildings.roofs._thin`)."""
    from recon3d.buildings.roofs import _thin

    if len(points) <= max_density * area:
        return points
    xyz = points[np.lexsort((points[:, 2], points[:, 1], points[:, 0]))]
    return xyz[_thin(xyz, math.sqrt(area / len(xyz)), max_density)]


def _attempt(lod: str, build, reasons: dict[str, str], codes: dict[str, tuple[int, ...]]):
    """``build()``, or None with the reason recorded in ``reasons[lod]`` (and the
    failed check's codes in ``codes[lod]``); a bug is logged and costs only this LoD,
    never the building its LoD1."""
    try:
        return build()
    except LodFailure as exc:
        reasons[lod] = exc.reason
        if exc.codes:
            codes[lod] = exc.codes
        log.debug("LoD%s not built: %s", lod, exc)
    except Exception:
        reasons[lod] = "internal_error"
        log.warning("LoD%s failed", lod, exc_info=True)
    return None


def _lod22(grid, fp, seg, roof_pts, g, u, cfg) -> tuple[Solid, float]:
    """The LoD2.2 solid over the segmented planes and its roof RMS, or LodFailure."""
    if seg.too_many_planes:
        raise LodFailure("too_many_planes", f"{len(seg.planes)} planes")
    if seg.coverage < 0.5:
        raise LodFailure("low_coverage", f"{seg.coverage:.0%} of the roof points on a plane")
    planes = [p.plane for p in seg.planes]
    try:
        solid, parts = _roofed(grid, fp, planes, g, u, intersect=True, points=roof_pts)
    except LodFailure as exc:
        if exc.reason != "invalid_mesh":
            raise
        # slivers and specks of roof parts are what usually breaks the shell: once more
        # without them, before falling back to LoD1.3
        log.debug("LoD2.2 retried without small parts: %s", exc)
        solid, parts = _roofed(grid, fp, planes, g, u, intersect=True, coarse=True, points=roof_pts)
    rms = partition_rms(parts, planes, roof_pts, u.height(1.0))
    if not rms <= u.height(getattr(cfg, "max_roof_rms", 0.5)):
        raise LodFailure("poor_fit", f"roof RMS {rms:.2f}")
    return solid, rms


def _lod13_of(grid, fp, seg, roof_pts, g, u, cfg) -> Solid:
    """LoD1.3 over the plane regions, or over height terraces when planes hold less
    than half the roof points (a spire)."""
    if seg.coverage >= 0.5:
        return _lod13(grid, fp, roof_pts, seg, g, u, cfg)
    levels = height_levels(roof_pts, grid.cell, u.height(getattr(cfg, "lod13_step", 1.0)))
    # no smallest area: the top terraces of a spire are a cell or two wide
    level_grid = label_grid(fp, roof_pts, levels, grid.cell, grid.cell**2)
    return _lod13(level_grid, fp, roof_pts, None, g, u, cfg, labels=levels)


def _segment(roof_pts, fp, params, u):
    """(segmentation, label grid, reason or None) of the roof points."""
    from recon3d.buildings.roofs import segment_roof

    if len(roof_pts) < max(params.min_points, 4):
        return None, None, "too_few_points"
    seg = segment_roof(roof_pts, params, footprint=fp)
    if not seg.planes:
        return seg, None, "too_few_points" if len(roof_pts) < seg.min_points else "no_roof_planes"
    cell = float(np.clip(1.5 * seg.spacing, u.length(0.25), u.length(1.0)))
    planes = [p.plane for p in seg.planes]
    grid = label_grid(fp, roof_pts, seg.labels, cell, max(u.area(1.0), 0.5 * params.min_plane_area), planes=planes, step=2 * params.distance)
    return seg, grid, None


def lod22_solid(
    footprint: shapely.Polygon,
    points: np.ndarray,
    labels: np.ndarray,
    planes: list[np.ndarray],
    ground_z: float,
    *,
    cell: float,
    units=None,
) -> Solid:
    """LoD2.2 solid from labelled roof points and their planes (all local coordinates).

    Parameters
    ----------
    footprint : shapely.Polygon
        Local coordinates.
    points : (n, 3) float
        Roof points; ``labels`` gives each one's plane index (-1: none).
    planes : list of (4,) float
        ``(a, b, c, d)`` with ``c > 0``.
    ground_z : float
        Floor height (local).
    cell : float
        Raster cell assigning the footprint to planes.

    Raises
    ------
    ValueError
        When the planes do not make a valid solid (its message holds the reason code).
    """
    from recon3d.core.geo import Units

    u = units or Units()
    try:
        grid = label_grid(footprint, points, labels, cell, u.area(1.0))
        planes = [np.asarray(p, float) for p in planes]
        return _roofed(grid, footprint, planes, ground_z, u, intersect=True, points=points)[0]
    except LodFailure as exc:
        raise ValueError(str(exc)) from None


def lod13_solid(
    footprint: shapely.Polygon,
    points: np.ndarray,
    labels: np.ndarray,
    ground_z: float,
    *,
    cell: float,
    step: float = 1.0,
    units=None,
) -> Solid:
    """LoD1.3 solid: one flat height per labelled region (local coordinates).

    Neighbouring regions whose heights (70th percentile of their points) differ by
    less than ``step`` are merged. See :func:`lod22_solid` for the parameters.
    """
    from recon3d.config import LodConfig
    from recon3d.core.geo import Units

    u = units or Units()
    grid = label_grid(footprint, points, labels, cell, u.area(1.0))
    try:
        cfg = LodConfig(lod13_step=step)
        return _lod13(grid, footprint, points, None, ground_z, u, cfg, labels=labels)
    except LodFailure as exc:
        raise ValueError(str(exc)) from None


# --------------------------------------------------------------------------- internals


def _issues(solid: Solid, u) -> list:
    """The polygon shell's val3dity issues, then (when it has none) those of the triangles
    every export is written from: a building is only kept when both are closed."""
    from recon3d.quality.meshcheck import check_solid, triangle_issues

    return check_solid(solid, planarity_tol=u.length(0.01), snap=u.length(0.001)) or triangle_issues(solid)


def _codes(issues: list) -> tuple[int, ...]:
    """The distinct val3dity codes of a check's issues, ascending."""
    return tuple(sorted({int(i.code) for i in issues}))


def _roofed(grid: RoofGrid, fp, planes: list[np.ndarray], g: float, u, *, intersect: bool, coarse: bool = False,
            points: np.ndarray | None = None):
    """The validated solid of the raster regions (LoD2.2: re-cut along plane intersections,
    each part on the plane its ``points`` lie on) and the regions, (polygon, plane index)
    pairs, it was built from. ``coarse`` also merges parts smaller than a 2 x 2 block of
    grid cells or thinner than 10 cm."""
    regions = grid_regions(grid, fp)
    if intersect and len(regions) > 1:
        regions = arrangement(regions, planes, fp, grid, u)
        if points is not None:
            regions = refit_parts(regions, planes, points, u.height(1.0))
    if coarse:
        regions = absorb_small(regions, (2.0 * grid.cell) ** 2, u.length(0.1))
    regions = absorb_small(regions, (0.5 * grid.cell) ** 2, u.length(0.02))
    regions = open_pinches(regions, u.length(0.05), u.length(0.004))
    regions = open_crossings(regions, u.length(0.05), u.length(0.004))
    if not regions:
        raise LodFailure("invalid_mesh", "no region left in the footprint")
    solid = partition_solid(regions, planes, g, u)
    issues = _issues(solid, u)
    if issues:
        raise LodFailure("invalid_mesh", "; ".join(f"{i.code} {i.detail}" for i in issues[:3]), _codes(issues))
    return solid, regions


def _lod13(grid: RoofGrid, fp, points, seg, g, u, cfg, *, labels=None) -> Solid:
    """LoD1.3 from a label grid (roof planes, or height terraces): one flat height per
    region, similar neighbours merged."""
    lab = seg.labels if seg is not None else np.asarray(labels)
    nl = int(max(grid.labels.max(), lab.max())) + 1
    heights = np.full(nl, np.nan)
    for k in range(nl):
        z = points[lab == k, 2]
        if len(z):
            heights[k] = np.percentile(z, 70)
    used = [k for k in range(nl) if (grid.labels == k).any() and np.isfinite(heights[k])]
    if not used:
        raise LodFailure("no_roof_planes")
    # merge neighbouring labels closer than lod13_step (union-find over touching cells)
    sets = MinRootSets(nl)
    step = u.height(getattr(cfg, "lod13_step", 1.0))
    lab_grid = grid.labels
    pairs = set()
    for a, b in ((lab_grid[:, :-1], lab_grid[:, 1:]), (lab_grid[:-1, :], lab_grid[1:, :])):
        m = (a >= 0) & (b >= 0) & (a != b)
        pairs |= set(zip(a[m].tolist(), b[m].tolist(), strict=True))
    for a, b in sorted(pairs, key=lambda ab: abs(heights[ab[0]] - heights[ab[1]])):
        ra, rb = sets.find(a), sets.find(b)
        if ra != rb and abs(heights[ra] - heights[rb]) < step:
            root = sets.union(ra, rb)
            members = [k for k in range(nl) if sets.find(k) == root]
            z = points[np.isin(lab, members), 2]
            heights[root] = np.percentile(z, 70) if len(z) else heights[root]
    root = np.array([sets.find(k) for k in range(nl)])
    merged = np.where(lab_grid >= 0, root[np.maximum(lab_grid, 0)], -1)
    planes = [
        np.array([0.0, 0.0, 1.0, -max(h, g + u.height(0.5))]) if np.isfinite(h) else None
        for h in heights
    ]
    if any(planes[k] is None for k in np.unique(merged[merged >= 0])):
        raise LodFailure("no_roof_planes")
    point_labels = np.where(lab >= 0, root[np.maximum(lab, 0)], -1)
    merged = unpinch(merged, grid.inside)
    merged_grid = RoofGrid(merged, grid.inside, grid.transform, grid.cell, grid.xy, point_labels)
    return _roofed(merged_grid, fp, planes, g, u, intersect=False)[0]


