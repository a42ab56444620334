"""Building solids by level of detail.

LoD1 is the footprint extruded from the terrain to a representative roof height: a
prism with one ground surface, one roof surface and one wall per footprint edge,
courtyards included. LoD1.3 (one flat height per roof part) and LoD2.2 (roof planes,
step walls) are assembled from a planar partition of the footprint, see the section
below :func:`lod1_solid`; :func:`build_lods` builds them with the fallback chain
LoD2.2 -> LoD1.3 -> LoD1. Solids are built in the city model's local frame so that
float32 consumers (glTF, OBJ importers) keep millimetres.
"""

from __future__ import annotations

import logging
import math as _math
from typing import NamedTuple

import numpy as np
import shapely

from recon3d.core.city import Solid
from recon3d.core.geo import LocalFrame
from recon3d.core.memory import available_memory

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


def clean_footprint(polygon: shapely.Polygon, tolerance: float) -> shapely.Polygon | None:
    """Footprint ready for extrusion: valid, repeated and collinear vertices removed,
    exterior counter-clockwise and holes clockwise. None when nothing with area is left.
    """
    poly = shapely.make_valid(shapely.remove_repeated_points(polygon, tolerance))
    parts = [g for g in getattr(poly, "geoms", [poly]) if g.geom_type == "Polygon" and g.area > 0]
    if not parts:
        return None
    poly = max(parts, key=lambda g: g.area).simplify(0.0)
    if poly.is_empty or poly.area <= 0 or len(poly.exterior.coords) < 4:
        return None
    return shapely.orient_polygons(poly)


def lod1_solid(footprint: shapely.Polygon, z0: float, z1: float, frame: LocalFrame) -> Solid:
    """The footprint extruded from height ``z0`` to ``z1`` (world heights).

    Parameters
    ----------
    footprint : shapely.Polygon
        Clean polygon (see :func:`clean_footprint`) in world coordinates.
    z0, z1 : float
        Floor and roof heights, ``z1 > z0``.
    frame : LocalFrame

    Returns
    -------
    Solid
        Outward-oriented surfaces: ground, roof, then one wall per edge.
    """
    if not z1 > z0:
        raise ValueError(f"roof height {z1} must be above floor height {z0}")
    rings = [np.asarray(footprint.exterior.coords)[:-1, :2]]
    rings += [np.asarray(r.coords)[:-1, :2] for r in footprint.interiors]
    sizes = [len(r) for r in rings]
    xy = np.concatenate(rings)
    n = len(xy)
    bottom = np.column_stack([xy, np.full(n, z0)])
    top = np.column_stack([xy, np.full(n, z1)])
    vertices = frame.to_local(np.concatenate([bottom, top]))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    ring_idx = [np.arange(s, s + k) for s, k in zip(starts, sizes, strict=True)]

    surfaces = [[r[::-1] for r in ring_idx], [r + n for r in ring_idx]]
    semantics = ["GroundSurface", "RoofSurface"]
    for r in ring_idx:
        nxt = np.roll(r, -1)
        quads = np.column_stack([r, nxt, nxt + n, r + n])
        surfaces += [[q] for q in quads]
        semantics += ["WallSurface"] * len(quads)
    # rings of a valid polygon may touch at a vertex (a courtyard reaching the outline);
    # one shared vertex keeps every edge used exactly twice, so the shell stays closed
    vertices, inverse = np.unique(vertices, axis=0, return_inverse=True)
    surfaces = [[inverse[r] for r in rings] for rings in surfaces]
    return Solid(vertices, surfaces, semantics)


# --------------------------------------------------------------------------- LoD1.3 and LoD2.2
#
# Both are built the same way, in the city model's local frame:
#
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
#    the label of the raster region they overlap most;
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
    """

    solids: dict
    roof_type: str
    status: str
    reason: str | None
    roof_rms: float
    planes: list


class _LodFailure(Exception):
    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


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
    if not np.isfinite(g) or not np.isfinite(r):
        return failed._replace(reason="no_points")
    if not r - g >= u.height(0.5):
        return failed._replace(reason="too_low")

    solids: dict[str, Solid] = {}
    reasons: dict[str, str] = {}
    lod1 = lod1_solid(footprint, g + oz, r + oz, frame)
    if _issues(lod1, u):
        return failed._replace(reason="invalid_mesh")
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
        built = _attempt("2.2", lambda: _lod22(grid, fp, seg, roof_pts, g, u, cfg), reasons)
        if built is not None:
            solids["2.2"], rms22 = built
    if ("1.3" in lods or "2.2" in reasons) and "1.3" not in reasons and grid is not None:
        built = _attempt("1.3", lambda: _lod13_of(grid, fp, seg, roof_pts, g, u, cfg), reasons)
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
    return LodResult(ordered, kind, status, None if status == "ok" else reasons.get(top), rms, planes)


def _attempt(lod: str, build, reasons: dict[str, str]):
    """``build()``, or None with the reason recorded in ``reasons[lod]``; a bug is
    logged and costs only this LoD, never the building its LoD1."""
    try:
        return build()
    except _LodFailure as exc:
        reasons[lod] = exc.reason
        log.debug("LoD%s not built: %s", lod, exc)
    except Exception:
        reasons[lod] = "internal_error"
        log.warning("LoD%s failed", lod, exc_info=True)
    return None


def _lod22(grid, fp, seg, roof_pts, g, u, cfg) -> tuple[Solid, float]:
    """The LoD2.2 solid over the segmented planes and its roof RMS, or _LodFailure."""
    if seg.too_many_planes:
        raise _LodFailure("too_many_planes", f"{len(seg.planes)} planes")
    if seg.coverage < 0.5:
        raise _LodFailure("low_coverage", f"{seg.coverage:.0%} of the roof points on a plane")
    planes = [p.plane for p in seg.planes]
    try:
        solid, parts = _roofed(grid, fp, planes, g, u, intersect=True)
    except _LodFailure as exc:
        if exc.reason != "invalid_mesh":
            raise
        # slivers and specks of roof parts are what usually breaks the shell: once more
        # without them, before falling back to LoD1.3
        log.debug("LoD2.2 retried without small parts: %s", exc)
        solid, parts = _roofed(grid, fp, planes, g, u, intersect=True, coarse=True)
    rms = _partition_rms(parts, planes, roof_pts, u.height(1.0))
    if not rms <= u.height(getattr(cfg, "max_roof_rms", 0.5)):
        raise _LodFailure("poor_fit", f"roof RMS {rms:.2f}")
    return solid, rms


def _lod13_of(grid, fp, seg, roof_pts, g, u, cfg) -> Solid:
    """LoD1.3 over the plane regions, or over height terraces when planes hold less
    than half the roof points (a spire)."""
    if seg.coverage >= 0.5:
        return _lod13(grid, fp, roof_pts, seg, g, u, cfg)
    levels = _height_levels(roof_pts, grid.cell, u.height(getattr(cfg, "lod13_step", 1.0)))
    # no smallest area: the top terraces of a spire are a cell or two wide
    level_grid = _label_grid(fp, roof_pts, levels, grid.cell, grid.cell**2)
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
    grid = _label_grid(fp, roof_pts, seg.labels, cell, max(u.area(1.0), 0.5 * params.min_plane_area), planes=planes, step=2 * params.distance)
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
        grid = _label_grid(footprint, points, labels, cell, u.area(1.0))
        planes = [np.asarray(p, float) for p in planes]
        return _roofed(grid, footprint, planes, ground_z, u, intersect=True)[0]
    except _LodFailure as exc:
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
    grid = _label_grid(footprint, points, labels, cell, u.area(1.0))
    try:
        cfg = LodConfig(lod13_step=step)
        return _lod13(grid, footprint, points, None, ground_z, u, cfg, labels=labels)
    except _LodFailure as exc:
        raise ValueError(str(exc)) from None


# --------------------------------------------------------------------------- internals


class _Grid(NamedTuple):
    labels: np.ndarray  # (h, w) int, -1 outside the footprint
    inside: np.ndarray  # (h, w) bool
    transform: object  # affine.Affine
    cell: float
    xy: np.ndarray  # (n, 2) the roof points in plan
    point_labels: np.ndarray  # (n,) their labels, -1 for none


def _issues(solid: Solid, u) -> list:
    from recon3d.quality.meshcheck import check_solid

    return check_solid(solid, planarity_tol=u.length(0.01), snap=u.length(0.001))


def _label_grid(fp, points, labels, cell, min_area, *, planes=None, step=0.5) -> _Grid:
    """Raster of plane labels over the footprint (every touched cell labelled).

    With the ``planes`` of the labels, the clean-up (majority filter, small patches)
    never moves a cell onto a plane more than ``step`` off its points while its own
    plane fits them: a strip of roof one cell wide (the steep eave of a mansard beside
    a lower annex) would otherwise go to the lower neighbour and drop its points by
    the whole step.
    """
    import affine
    import rasterio.features
    from scipy import ndimage

    minx, miny, maxx, maxy = fp.bounds
    x0 = _math.floor(minx / cell) * cell - cell
    y1 = _math.ceil(maxy / cell) * cell + cell
    w = int(_math.ceil((maxx - x0) / cell)) + 1
    h = int(_math.ceil((y1 - miny) / cell)) + 1
    transform = affine.Affine(cell, 0.0, x0, 0.0, -cell, y1)
    inside = rasterio.features.rasterize(
        [(fp, 1)], out_shape=(h, w), transform=transform, all_touched=True, dtype="uint8"
    ).astype(bool)
    lab = np.asarray(labels)
    keep = lab >= 0
    if not keep.any():
        raise _LodFailure("no_roof_planes")
    nl = int(lab.max()) + 1
    need = h * w * (nl * 12 + 64)  # votes (int64) and one-hot scores (float32) per plane, the masks
    if need > available_memory():
        raise _LodFailure("too_large", f"a roof grid of {h} x {w} cells and {nl} planes needs {need / 2**30:.1f} GiB")
    col = np.clip(((points[keep, 0] - x0) / cell).astype(np.int64), 0, w - 1)
    row = np.clip(((y1 - points[keep, 1]) / cell).astype(np.int64), 0, h - 1)
    votes = np.bincount((row * w + col) * nl + lab[keep], minlength=h * w * nl).reshape(h * w, nl)
    grid = np.where(votes.max(axis=1) > 0, votes.argmax(axis=1), -1).reshape(h, w)
    grid[~inside] = -1
    grid = _fill(grid, inside)
    # majority filter (3 x 3) against single-cell noise, then small patches to neighbours
    onehot = np.stack([(grid == k) for k in range(nl)]).astype(np.float32)
    score = ndimage.uniform_filter(onehot, size=(1, 3, 3), mode="constant")
    smooth = np.where(inside, score.argmax(axis=0), -1)
    smooth[inside & (score.max(axis=0) <= 0)] = grid[inside & (score.max(axis=0) <= 0)]
    raw, grid = grid, smooth
    min_cells = max(1, int(round(min_area / cell**2)))
    for _ in range(2):
        small = np.zeros_like(inside)
        for k in np.unique(grid[inside]):
            comp, count = ndimage.label(grid == k)
            if count:
                sizes = np.bincount(comp.ravel())
                sizes[0] = 0
                small |= (sizes < min_cells)[comp] & (comp > 0)
        if not small.any() or small[inside].all():
            break
        grid[small] = -1
        grid = _fill(grid, inside)
    if planes is not None:
        grid = _keep_fitting(grid, raw, points[keep], row * w + col, planes, step)
    point_labels = np.where(keep, lab, -1)
    return _Grid(_unpinch(grid, inside), inside, transform, cell, points[:, :2], point_labels)


def _keep_fitting(smooth, raw, points, flat, planes, step) -> np.ndarray:
    """``smooth`` with the cells set back to their ``raw`` label where most of the
    cell's points lie on the raw label's plane (within ``step`` / 2) and most lie more
    than ``step`` off the plane the clean-up gave the cell.

    ``points`` (n, 3), the roof points on a plane, fall in the cells ``flat`` (n,)
    (row * width + col) of the grids.
    """
    changed = ((smooth != raw) & (raw >= 0) & (smooth >= 0)).ravel()
    moved = changed[flat]
    if not moved.any():
        return smooth
    cell = flat[moved]
    x, y, z = points[moved].T
    coef = np.asarray(planes)
    on_raw = np.abs(_height(coef[raw.ravel()[cell]].T, x, y) - z) < 0.5 * step
    off_new = np.abs(_height(coef[smooth.ravel()[cell]].T, x, y) - z) > step
    count = np.bincount(cell, minlength=raw.size)
    back = (2 * np.bincount(cell, weights=on_raw, minlength=raw.size) > count) & (
        2 * np.bincount(cell, weights=off_new, minlength=raw.size) > count
    )
    out = smooth.copy().ravel()
    out[back] = raw.ravel()[back]
    return out.reshape(smooth.shape)


def _unpinch(grid: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Labels without checkerboard 2 x 2 windows (two cells of one label touching only
    at a corner). Such a corner would become a vertex where one roof part touches
    itself, and the walls around it an edge shared by four surfaces (val3dity 304);
    one of the two other cells takes the label instead."""
    grid = grid.copy()
    for _ in range(20):
        a, b, c, d = grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]
        main = (a == d) & (a >= 0) & (b != a) & (c != a)
        anti = (b == c) & (b >= 0) & (a != b) & (d != b) & ~main
        if not (main.any() or anti.any()):
            break
        r, q = np.nonzero(main)
        take = inside[r, q + 1]
        grid[r[take], q[take] + 1] = grid[r[take], q[take]]
        r2, q2 = np.nonzero(anti)
        take2 = inside[r2, q2]
        grid[r2[take2], q2[take2]] = grid[r2[take2], q2[take2] + 1]
    return grid


def _fill(grid: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Unlabelled cells inside the footprint take the nearest labelled cell's label."""
    from scipy import ndimage

    known = grid >= 0
    if not known.any():
        raise _LodFailure("no_roof_planes")
    if (known | ~inside).all():
        return grid
    idx = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
    out = grid[idx[0], idx[1]]
    out[~inside] = -1
    return out


def _regions(grid: _Grid, fp) -> list[tuple[shapely.Polygon, int]]:
    """Polygons of the raster regions: shared edges simplified together, clipped by the footprint."""
    import rasterio.features
    from shapely.geometry import shape

    geoms, values = [], []
    for geom, value in rasterio.features.shapes(
        grid.labels.astype(np.int32), mask=grid.inside, connectivity=4, transform=grid.transform
    ):
        geoms.append(shape(geom))
        values.append(int(value))
    if len(geoms) > 1:
        geoms, values = _simplify_shared(geoms, values, grid.cell, grid.xy, grid.point_labels)
    parts: list[tuple[shapely.Polygon, int]] = []
    for geom, value in zip(geoms, values, strict=True):
        clipped = shapely.intersection(geom, fp)
        for piece in getattr(clipped, "geoms", [clipped]):
            if piece.geom_type == "Polygon" and piece.area > 0:
                parts.append((piece, value))
    return parts


def _simplify_shared(geoms, values, tolerance, xy=None, point_labels=None):
    """Straighten the edges neighbouring regions share, keeping the outer boundary and
    the junctions; returns a coverage again.

    The boundaries are noded into chains between junctions. Each shared chain is
    simplified (Douglas-Peucker, ``tolerance``) and, where the points of the two
    regions meet along it, every segment is moved onto the line fitted through the
    midpoints of neighbouring point pairs from either side (the wall of a height
    jump lies half-way between the last points of the upper and the first of the
    lower roof); a chain end on the outer boundary slides along it. Everything is
    re-noded and polygonized, each face takes the label of the region it overlaps
    most, and faces of one label that touch are merged.
    """
    outline = shapely.union_all(geoms)
    chains = shapely.line_merge(shapely.union_all([g.boundary for g in geoms]))
    chains = list(getattr(chains, "geoms", [chains]))
    rim = outline.boundary
    mids = _pair_midpoints(xy, point_labels, tolerance) if xy is not None else {}
    tree = shapely.STRtree(geoms)
    lines = []
    for chain in chains:
        mid = shapely.line_interpolate_point(chain, 0.5, normalized=True)
        if shapely.distance(mid, rim) < 1e-9 * max(1.0, tolerance):
            lines.append(chain)
            continue
        simple = shapely.simplify(chain, tolerance, preserve_topology=False)
        near = tree.query(mid, predicate="dwithin", distance=1e-9 * max(1.0, tolerance))
        pair = tuple(sorted({values[int(k)] for k in near}))
        if len(pair) == 2 and pair in mids:
            simple = _fit_chain(simple, mids[pair], rim, tolerance)
        lines.append(simple)
    faces = list(shapely.polygonize(list(shapely.get_parts(shapely.union_all(lines)))).geoms)
    if not faces:
        return geoms, values
    pieces = _faces_by_label(faces, tree, geoms, values)
    return [p for p, _ in pieces], [v for _, v in pieces]


def _faces_by_label(faces, tree, geoms, values) -> list[tuple[shapely.Polygon, int]]:
    """Give each face the label of the region it overlaps most; union the faces per label.

    Parameters
    ----------
    faces : list of shapely.Polygon
        A partition (polygonized noded lines).
    tree : shapely.STRtree
        Over ``geoms``, the labelled regions; ``values[i]`` is the label of ``geoms[i]``.

    Returns
    -------
    list of (Polygon, label), by label.
    """
    by_label: dict[int, list] = {}
    for face in faces:
        cand = tree.query(face)
        if not len(cand):
            continue
        areas = [shapely.intersection(face, geoms[c]).area for c in cand]
        by_label.setdefault(values[int(cand[int(np.argmax(areas))])], []).append(face)
    return [
        (piece, label)
        for label in sorted(by_label)
        for piece in shapely.get_parts(shapely.union_all(by_label[label]))
        if piece.geom_type == "Polygon" and piece.area > 0
    ]


def _pair_midpoints(xy, labels, cell) -> dict[tuple[int, int], np.ndarray]:
    """Midpoints of close point pairs with different labels, by (label, label)."""
    from scipy.spatial import cKDTree

    keep = labels >= 0
    if keep.sum() < 2:
        return {}
    pts, lab = xy[keep], labels[keep]
    pairs = cKDTree(pts).query_pairs(1.5 * cell, output_type="ndarray")
    if not len(pairs):
        return {}
    la, lb = lab[pairs[:, 0]], lab[pairs[:, 1]]
    diff = la != lb
    pairs, la, lb = pairs[diff], la[diff], lb[diff]
    mid = 0.5 * (pts[pairs[:, 0]] + pts[pairs[:, 1]])
    key = np.minimum(la, lb) * (int(lab.max()) + 1) + np.maximum(la, lb)
    out = {}
    for k in np.unique(key):
        out[(int(k // (lab.max() + 1)), int(k % (lab.max() + 1)))] = mid[key == k]
    return out


def _fit_chain(chain, mids: np.ndarray, rim, cell):
    """A simplified chain with each segment moved onto the line fitted through the
    pair midpoints near it; inner vertices at the fitted lines' crossings, ends on the
    rim slid along it, other ends (junctions) kept."""
    c = shapely.get_coordinates(chain)
    if len(c) < 2:
        return chain
    seg_a, seg_b = c[:-1], c[1:]
    near = mids[shapely.contains_xy(chain.buffer(1.5 * cell), mids[:, 0], mids[:, 1])]
    if len(near) < 4:
        return chain
    # nearest segment of every midpoint
    d = seg_b - seg_a
    l2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-12)
    t = np.clip(np.einsum("kij,ij->ki", near[:, None, :] - seg_a[None], d) / l2, 0, 1)
    foot = seg_a[None] + t[..., None] * d[None]
    which = np.argmin(np.linalg.norm(near[:, None, :] - foot, axis=2), axis=1)
    lines = []
    for s in range(len(seg_a)):
        m = near[which == s]
        length = float(np.sqrt(l2[s]))
        if len(m) >= 4 and length > cell:
            centre = m.mean(axis=0)
            direction = np.linalg.svd(m - centre, full_matrices=False)[2][0]
            if abs(direction @ d[s]) / length < np.cos(np.radians(20)):
                direction = d[s] / length  # the points do not follow this segment
                centre = centre - ((centre - seg_a[s]) @ direction) * direction + 0.0
            lines.append((centre, direction))
        else:
            lines.append((seg_a[s], d[s] / max(length, 1e-12)))
    out = c.copy()
    for k in range(1, len(c) - 1):
        p = _cross_lines(lines[k - 1], lines[k])
        if p is not None and np.linalg.norm(p - c[k]) < 3 * cell:
            out[k] = p
    for end, seg in ((0, 0), (len(c) - 1, len(seg_a) - 1)):
        if shapely.distance(shapely.Point(c[end]), rim) > 1e-9 * max(1.0, cell):
            continue
        centre, direction = lines[seg]
        probe = shapely.LineString([centre - 1e3 * cell * direction, centre + 1e3 * cell * direction])
        hits = shapely.get_coordinates(shapely.intersection(probe, rim))
        if len(hits):
            best = hits[np.argmin(np.linalg.norm(hits - c[end], axis=1))]
            if np.linalg.norm(best - c[end]) < 3 * cell:
                out[end] = best
    if len(out) == 2 and np.allclose(out[0], out[1]):
        return chain
    return shapely.LineString(out)


def _cross_lines(a, b):
    """Crossing of two lines (point, unit direction); None when nearly parallel."""
    (p, d), (q, e) = a, b
    det = d[0] * (-e[1]) - d[1] * (-e[0])
    if abs(det) < np.sin(np.radians(15)):
        return None
    r = q - p
    t = (r[0] * (-e[1]) - r[1] * (-e[0])) / det
    return p + t * d


def _absorb_small(parts, min_area, min_width=0.0):
    """Pieces smaller than ``min_area`` or thinner than ``min_width`` (2 area / perimeter)
    join the neighbour they share most boundary with."""

    def small(p):
        return p.area < min_area or 2.0 * p.area < min_width * p.length

    big = [(p, v) for p, v in parts if not small(p)]
    tiny = [p for p, v in parts if small(p)]
    if not big:
        return parts
    for piece in sorted(tiny, key=lambda p: -p.area):
        shared = [shapely.intersection(piece.boundary, b.boundary).length for b, _ in big]
        k = int(np.argmax(shared))
        if shared[k] <= 0:
            continue
        merged = shapely.union(big[k][0], piece)
        polys = [g for g in getattr(merged, "geoms", [merged]) if g.geom_type == "Polygon"]
        if len(polys) == 1:
            big[k] = (polys[0], big[k][1])
    return big


def _roofed(grid: _Grid, fp, planes: list[np.ndarray], g: float, u, *, intersect: bool, coarse: bool = False):
    """The validated solid of the raster regions (LoD2.2: re-cut along plane intersections)
    and the regions, (polygon, plane index) pairs, it was built from. ``coarse`` also
    merges parts smaller than a 2 x 2 block of grid cells or thinner than 10 cm."""
    regions = _regions(grid, fp)
    if intersect and len(regions) > 1:
        regions = _arrangement(regions, planes, fp, grid, u)
    if coarse:
        regions = _absorb_small(regions, (2.0 * grid.cell) ** 2, u.length(0.1))
    regions = _absorb_small(regions, (0.5 * grid.cell) ** 2, u.length(0.02))
    regions = _open_pinches(regions, u.length(0.05), u.length(0.004))
    regions = _open_crossings(regions, u.length(0.05), u.length(0.004))
    if not regions:
        raise _LodFailure("invalid_mesh", "no region left in the footprint")
    solid = _partition_solid(regions, planes, g, u)
    issues = _issues(solid, u)
    if issues:
        raise _LodFailure("invalid_mesh", "; ".join(f"{i.code} {i.detail}" for i in issues[:3]))
    return solid, regions


def _partition_rms(regions, planes, points: np.ndarray, outlier: float) -> float:
    """Robust RMS of the vertical distances of points to the roof parts above them (the
    same as ``quality.roofs.roof_rms`` on the solid, up to the 5 mm height snapping,
    without triangulating it)."""
    if not len(points):
        return float("nan")
    polys = [p for p, _ in regions]
    pi, ri = shapely.STRtree(polys).query(shapely.points(points[:, :2]), predicate="intersects")
    if not len(pi):
        return float("nan")
    labels = np.array([k for _, k in regions])[ri]
    plane = np.asarray(planes, dtype=np.float64)[labels]
    roof = -(plane[:, 0] * points[pi, 0] + plane[:, 1] * points[pi, 1] + plane[:, 3]) / plane[:, 2]
    top = np.full(len(points), -np.inf)
    np.maximum.at(top, pi, roof)
    r = points[:, 2] - top
    r = r[np.isfinite(r) & (np.abs(r) <= outlier)]
    return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")


def _partition_solid(regions, planes, g: float, u) -> Solid:
    """Closed solid over a planar partition of the footprint, one plane per part.

    Every part becomes a roof surface at its plane's heights; wherever two parts
    have different heights along their common edge a vertical wall joins them, the
    outline gets walls down to ``g`` and the footprint a ground surface. The
    partition is made conforming first (2 mm grid, vertices lying on an edge
    inserted into it, edges split where two planes cross along them), and heights
    closer than 5 mm at one vertex are made equal, so every edge of the shell is
    shared by exactly two surfaces and no sliver wall is left.
    """
    grid = u.length(0.002)
    eps = u.height(0.005)
    min_wall = u.height(0.2)
    faces, labels = [], []
    snapped = shapely.set_precision(np.array([p for p, _ in regions], dtype=object), grid)
    for poly, (_, k) in zip(snapped, regions, strict=True):
        for part in shapely.get_parts(poly):
            if part.geom_type == "Polygon" and part.area > 0:
                faces.append(shapely.orient_polygons(part))
                labels.append(k)
    if not faces:
        raise _LodFailure("invalid_mesh", "no region left in the footprint")
    ring_xy = [[np.asarray(r.coords)[:-1, :2] for r in (f.exterior, *f.interiors)] for f in faces]
    all_xy = np.concatenate([r for rings in ring_xy for r in rings])
    coords, inverse = np.unique(all_xy, axis=0, return_inverse=True)
    inverse = _merge_close(coords, 1.5 * grid)[inverse.reshape(-1)]
    rings, pos, keep = [], 0, []
    for f, rr in enumerate(ring_xy):
        ids = []
        for r in rr:
            ids.append(_clean_ring(inverse[pos : pos + len(r)]))
            pos += len(r)
        ids = [ids[0]] + [r for r in ids[1:] if len(r) >= 3]
        if len(ids[0]) >= 3:
            rings.append(ids)
            keep.append(f)
    labels = [labels[f] for f in keep]
    if not rings:
        raise _LodFailure("invalid_mesh", "no region left in the footprint")
    # a vertex within the merge distance of an edge lies on it (else a sliver gap too thin
    # for a valid ring opens between two parts); inserted on both edges of a narrow turn
    # it makes a spike (a, b, a): clean again
    rings = [[_clean_ring(_insert_on_edges(r, coords, 1.5 * grid)) for r in rr] for rr in rings]
    plane_of = [np.asarray(planes[k], dtype=np.float64) for k in labels]
    # split shared edges where the two planes cross (a wall changing sides)
    for _ in range(3):
        extra = _crossings(rings, coords, plane_of, eps)
        if not len(extra):
            break
        extra = np.round(extra / grid) * grid
        coords = np.concatenate([coords, extra])
        first = len(coords) - len(extra)
        rings = [[_clean_ring(_insert_on_edges(r, coords, grid, new_from=first)) for r in rr] for rr in rings]
    # heights per (face, vertex), clustered per vertex
    entries = []
    for f, rr in enumerate(rings):
        ids = np.unique(np.concatenate(rr))
        h = _height(plane_of[f], coords[ids, 0], coords[ids, 1])
        if np.any(h < g + min_wall - eps):
            raise _LodFailure("poor_fit", "a roof plane reaches down to the ground")
        entries.append(np.column_stack([ids, np.full(len(ids), f), h]))
    directed = {}
    for f, rr in enumerate(rings):
        for r in rr:
            for a, b in zip(r.tolist(), np.roll(r, -1).tolist(), strict=True):
                if (a, b) in directed:
                    raise _LodFailure("invalid_mesh", "two parts overlap along an edge")
                directed[(a, b)] = f
    boundary = [(a, b, f) for (a, b), f in directed.items() if (b, a) not in directed]
    ground_ids = np.unique([a for a, _, _ in boundary] + [b for _, b, _ in boundary])
    table = np.concatenate(entries)
    n_ground = len(ground_ids)
    ground_rows = np.column_stack([ground_ids, np.full(n_ground, -1), np.full(n_ground, g)])
    table = np.concatenate([table, ground_rows])
    order = np.lexsort((table[:, 2], table[:, 0]))
    table = table[order]
    vid = table[:, 0].astype(np.int64)
    new = np.r_[True, (vid[1:] != vid[:-1]) | (np.diff(table[:, 2]) > eps)]
    cluster = np.cumsum(new) - 1
    heights = np.bincount(cluster, weights=table[:, 2]) / np.bincount(cluster)
    is_ground = table[:, 1] < 0
    heights[cluster[is_ground]] = g
    owner = table[:, 1].astype(np.int64)
    cid = {(int(f), int(v)): int(c) for v, f, c in zip(vid, owner, cluster, strict=True)}
    column = {}
    for v, c in zip(vid.tolist(), cluster.tolist(), strict=True):
        col = column.setdefault(v, [])
        if not col or col[-1] != c:
            col.append(c)
    first_of = np.flatnonzero(new)
    verts = np.column_stack([coords[vid[first_of]], heights])

    def run(v: int, c0: int, c1: int) -> list[int]:
        col = column[v]
        i0, i1 = col.index(c0), col.index(c1)
        return col[i0 : i1 + 1] if i0 <= i1 else col[i1 : i0 + 1][::-1]

    surfaces, semantics = [], []
    for f, rr in enumerate(rings):
        surfaces.append([np.array([cid[(f, int(v))] for v in r]) for r in rr])
        semantics.append("RoofSurface")
    walls = []
    for (a, b), f in directed.items():
        other = directed.get((b, a), -1)
        if other >= 0 and other < f:
            continue  # each shared edge once
        top_a, top_b = cid[(f, a)], cid[(f, b)]
        low_a, low_b = cid[(other, a)], cid[(other, b)]
        ring = _dedupe(run(a, top_a, low_a) + run(b, low_b, top_b))
        if len(ring) >= 3:
            walls.append(np.array(ring))
    for w in _merge_walls(verts, walls, eps):
        surfaces.append(w)
        semantics.append("WallSurface")
    edges = np.array([[cid[(-1, b)], cid[(-1, a)]] for a, b, _ in boundary], dtype=np.int64)
    for rings_g in _face_rings(verts, edges, np.array([0.0, 0.0, -1.0])):
        surfaces.append(rings_g)
        semantics.append("GroundSurface")
    return Solid(verts, surfaces, semantics)


def _merge_walls(verts: np.ndarray, walls: list[np.ndarray], tol: float) -> list[list[np.ndarray]]:
    """Neighbouring walls in one vertical plane (within ``tol``) merged into one surface."""
    from recon3d.core.city import newell_normal

    n = len(walls)
    normals = np.zeros((n, 2))
    offsets = np.zeros(n)
    for i, w in enumerate(walls):
        nv = newell_normal(verts[w])[:2]
        norm = np.linalg.norm(nv)
        normals[i] = nv / norm if norm > 0 else 0.0
        offsets[i] = float(np.mean(verts[w][:, :2] @ normals[i]))
    sets = _MinRootSets(n)
    owner: dict[tuple[int, int], int] = {}
    for i, w in enumerate(walls):
        for a, b in zip(w.tolist(), np.roll(w, -1).tolist(), strict=True):
            j = owner.get((b, a))
            same = j is not None and normals[i] @ normals[j] > 0.99996
            if same and abs(offsets[i] - offsets[j]) < tol:
                sets.union(i, j)
            owner[(a, b)] = i
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(sets.find(i), []).append(i)
    out = []
    for members in groups.values():
        if len(members) == 1:
            out.append([walls[members[0]]])
            continue
        edges = {
            (a, b)
            for i in members
            for a, b in zip(walls[i].tolist(), np.roll(walls[i], -1).tolist(), strict=True)
        }
        rim = np.array(sorted(e for e in edges if (e[1], e[0]) not in edges), dtype=np.int64)
        normal = np.append(normals[members[0]], 0.0)
        try:
            out += _face_rings(verts, rim, normal)
        except _LodFailure:
            out += [[walls[i]] for i in members]
    return out


def _merge_close(coords: np.ndarray, tol: float) -> np.ndarray:
    """For every point, the index of the first point of its cluster (points within ``tol``)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(coords)
    pairs = cKDTree(coords).query_pairs(tol, output_type="ndarray")
    if not len(pairs):
        return np.arange(n)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    first = np.full(label.max() + 1, n)
    np.minimum.at(first, label, np.arange(n))
    return first[label]


def _clean_ring(ring: np.ndarray) -> np.ndarray:
    """Ring without consecutive repeats and without spikes (a, b, a)."""
    r = _dedupe(list(ring.tolist()))
    changed = True
    while changed and len(r) >= 3:
        changed = False
        n = len(r)
        for i in range(n):
            if r[i - 2] == r[i]:
                drop = {(i - 1) % n, i}
                r = _dedupe([v for k, v in enumerate(r) if k not in drop])
                changed = True
                break
    return np.array(r, dtype=np.int64)


def _open_pinches(regions, radius: float, tol: float):
    """Regions that touch themselves at a vertex (a hole touching the outline, two lobes
    meeting at a corner; vertices of non-consecutive ring positions closer than ``tol``,
    or a vertex closer than ``tol`` to an edge of the region it does not end: a neck
    that snapping the vertices closes) give the part of them within ``radius`` of that
    vertex to the neighbour covering
    most of the rest of that disc, so no part of the roof meets itself at a point (the
    walls there would share an edge four times, val3dity 304)."""
    from scipy.spatial import cKDTree

    regions = list(regions)
    failed: set[tuple[float, float]] = set()
    for _ in range(2 * len(regions) + 2):
        found = None
        for i, (poly, _) in enumerate(regions):
            rings = [
                _drop_close(np.asarray(r.coords)[:-1, :2], tol) for r in (poly.exterior, *poly.interiors)
            ]
            pts = np.concatenate(rings)
            ring_of = np.repeat(np.arange(len(rings)), [len(r) for r in rings])
            pos = np.concatenate([np.arange(len(r)) for r in rings])
            size = np.array([len(r) for r in rings])[ring_of]
            for a, b in cKDTree(pts).query_pairs(tol, output_type="ndarray"):
                step = abs(int(pos[a]) - int(pos[b]))
                if ring_of[a] != ring_of[b] or min(step, size[a] - step) > 1:
                    mid = 0.5 * (pts[a] + pts[b])
                    if (round(mid[0], 6), round(mid[1], 6)) not in failed:
                        found = (i, mid)
                        break
            if found is None:
                found = next(((i, v) for v in _necks(rings, tol) if (round(v[0], 6), round(v[1], 6)) not in failed), None)
            if found is not None:
                break
        if found is None:
            return regions
        i, p = found
        disc = shapely.Point(p).buffer(radius, quad_segs=2)
        poly, label = regions[i]
        sectors = [g for g in shapely.get_parts(shapely.intersection(poly, disc)) if g.area > 0]
        rest = shapely.difference(poly, disc)
        new = dict(enumerate(r for r, _ in regions))
        for sector in sectors:
            shared = [
                shapely.intersection(sector.boundary, q.buffer(tol)).length if j != i else 0.0
                for j, q in new.items()
            ]
            j = int(np.argmax(shared))
            grown = shapely.union(new[j], sector, grid_size=0.01 * tol) if shared[j] > 0 else None
            if grown is None or grown.geom_type != "Polygon":
                break
            new[j] = grown
        else:
            sectors = None
        if sectors is not None:  # cannot open it: the mesh check will decide
            failed.add((round(p[0], 6), round(p[1], 6)))
            continue
        parts = [g for g in shapely.get_parts(rest) if g.geom_type == "Polygon" and g.area > 0]
        out = [(new[j], regions[j][1]) for j in range(len(regions)) if j != i]
        regions = out[:i] + [(g, label) for g in parts] + out[i:]
    return regions


def _necks(rings: list[np.ndarray], tol: float) -> np.ndarray:
    """(k, 2) vertices of a region's rings closer than ``tol`` to one of its edges that
    does not end at them (its own ring's or another's)."""
    starts = np.concatenate(rings)
    ends = np.concatenate([np.roll(r, -1, axis=0) for r in rings])
    ring_of = np.repeat(np.arange(len(rings)), [len(r) for r in rings])
    first = np.concatenate([[0], np.cumsum([len(r) for r in rings])[:-1]])[ring_of]
    size = np.array([len(r) for r in rings])[ring_of]
    edges = shapely.linestrings(np.stack([starts, ends], axis=1))
    vertex, edge = shapely.STRtree(edges).query(shapely.points(starts), predicate="dwithin", distance=tol)
    # edge e runs from vertex e to the next vertex of its ring
    following = first[edge] + (edge - first[edge] + 1) % size[edge]
    incident = (vertex == edge) | (vertex == following)
    return starts[np.unique(vertex[~incident])]


def _open_crossings(regions, radius: float, tol: float):
    """Where four or more parts meet at one vertex (boundaries closer than ``tol``: a
    part whose straight edge runs through the vertex counts too), the part covering
    most of the disc of ``radius`` around it takes the whole disc, so only junctions
    of three are left. With heights going up and down around such a vertex (two
    ridges crossing off level), the four step walls there would share one vertical
    edge (val3dity 304); around a junction of three, every wall edge has two sides."""
    from scipy.spatial import cKDTree

    regions = list(regions)
    tried: set[tuple[float, float]] = set()  # each crossing once, opened or not
    for _ in range(2 * len(regions) + 2):
        rings = [(i, np.asarray(r.coords)[:-1, :2]) for i, (p, _) in enumerate(regions) for r in (p.exterior, *p.interiors)]
        pts = np.concatenate([xy for _, xy in rings])
        owner = np.concatenate([np.full(len(xy), i) for i, xy in rings])
        tree = shapely.STRtree([p.boundary for p, _ in regions])
        crossing = next(
            (
                pts[k]
                for k, near in enumerate(cKDTree(pts).query_ball_point(pts, tol))
                if len(set(owner[near])) >= 3
                and (round(pts[k][0] / tol), round(pts[k][1] / tol)) not in tried
                and len(tree.query(shapely.Point(pts[k]), predicate="dwithin", distance=tol)) >= 4
            ),
            None,
        )
        if crossing is None:
            return regions
        tried.add((round(crossing[0] / tol), round(crossing[1] / tol)))
        whole = shapely.union_all([p for p, _ in regions])
        disc = shapely.intersection(shapely.Point(crossing).buffer(radius, quad_segs=2), whole)
        j = int(np.argmax([shapely.intersection(p, disc).area for p, _ in regions]))
        out = []
        for i, (poly, label) in enumerate(regions):
            cut = shapely.union(poly, disc) if i == j else shapely.difference(poly, disc)
            parts = [g for g in shapely.get_parts(cut) if g.geom_type == "Polygon" and g.area > 0]
            if i == j and len(parts) != 1:
                break  # cannot open this one: the mesh check will decide
            out += [(g, label) for g in parts]
        else:
            regions = out
    return regions


def _drop_close(ring: np.ndarray, tol: float) -> np.ndarray:
    """Ring coordinates without runs of consecutive points closer than ``tol``."""
    keep = [0]
    for k in range(1, len(ring)):
        if np.hypot(*(ring[k] - ring[keep[-1]])) > tol:
            keep.append(k)
    if len(keep) > 1 and np.hypot(*(ring[keep[-1]] - ring[0])) <= tol:
        keep.pop()
    return ring[keep]


def _dedupe(ring: list[int]) -> list[int]:
    """Ring without consecutive repeats (cyclically)."""
    out = [v for i, v in enumerate(ring) if v != ring[i - 1]] if len(ring) > 1 else list(ring)
    return out


def _insert_on_edges(ring: np.ndarray, coords: np.ndarray, tol: float, new_from: int = 0) -> np.ndarray:
    """Ring with every vertex (index >= ``new_from``) lying within ``tol`` of one of its
    edges inserted into that edge, in order; consecutive repeats dropped."""
    cand = np.arange(new_from, len(coords))
    p = coords[ring]
    q = coords[np.roll(ring, -1)]
    d = q - p
    length2 = np.einsum("ij,ij->i", d, d)
    out = []
    c = coords[cand]
    for k in range(len(ring)):
        out.append(int(ring[k]))
        if length2[k] <= 0:
            continue
        t = ((c - p[k]) @ d[k]) / length2[k]
        near = (t > 1e-9) & (t < 1 - 1e-9)
        if not near.any():
            continue
        foot = p[k] + t[near, None] * d[k]
        dist = np.linalg.norm(c[near] - foot, axis=1)
        hit = dist <= tol
        if hit.any():
            ids = cand[near][hit]
            for j in ids[np.argsort(t[near][hit], kind="stable")]:
                if j != ring[k] and j != ring[(k + 1) % len(ring)]:
                    out.append(int(j))
    ring = np.array(_dedupe(out), dtype=np.int64)
    return ring


def _crossings(rings, coords, plane_of, eps) -> np.ndarray:
    """Points where two neighbouring parts' planes cross along their common edge."""
    owner = {}
    for f, rr in enumerate(rings):
        for r in rr:
            for a, b in zip(r.tolist(), np.roll(r, -1).tolist(), strict=True):
                owner[(a, b)] = f
    out = []
    for (a, b), f in owner.items():
        g = owner.get((b, a))
        if g is None or g < f:
            continue
        pa, pb = coords[a], coords[b]
        da = _height(plane_of[f], *pa) - _height(plane_of[g], *pa)
        db = _height(plane_of[f], *pb) - _height(plane_of[g], *pb)
        if da * db < 0 and abs(da) > eps and abs(db) > eps:
            out.append(pa + da / (da - db) * (pb - pa))
    return np.array(out).reshape(-1, 2)


def _height(plane, x, y):
    a, b, c, d = plane
    return -(a * np.asarray(x) + b * np.asarray(y) + d) / c


def _arrangement(regions, planes, fp, grid: _Grid, u) -> list[tuple[shapely.Polygon, int]]:
    """Regions re-cut so that neighbouring planes meet exactly where they intersect.

    Each edge two regions share is either an intersection (the line where their
    planes have equal heights lies within a few cells of the edge all along it: a
    ridge, hip or valley) or a height jump. The footprint is cut by the full
    intersection lines and by the jump edges (extended by a cell at both ends so they
    reach the lines), and every face of that arrangement takes the label of the
    raster region it overlaps most; faces of one label that touch are merged. Along
    an intersection line the two planes then have the same height, so the roofs
    meet without a wall; along a jump edge a vertical step wall joins them.

    An edge near the intersection line is still a jump when the points disagree:
    more than 10 % of the two regions' points near the edge (leaving out those
    fitting both planes) lying on the other plane's side of the line, e.g. a slope
    whose eave ends below the flat roof next to it.
    """
    cell = grid.cell
    near = max(2.5 * cell, u.length(0.75))
    plab = grid.point_labels
    polys = [p for p, _ in regions]
    labels = [k for _, k in regions]
    tree = shapely.STRtree(polys)
    x0, y0, x1, y1 = fp.bounds
    reach = 2.0 * float(np.hypot(x1 - x0, y1 - y0)) + 2.0 * cell
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    cuts, done = [], set()
    left, right = tree.query(polys, predicate="intersects")
    for i, j in zip(left.tolist(), right.tolist(), strict=True):
        if j <= i or labels[i] == labels[j]:
            continue
        shared = shapely.line_merge(shapely.intersection(polys[i].boundary, polys[j].boundary))
        pi, pj = planes[labels[i]], planes[labels[j]]
        grad = -pi[:2] / pi[2] + pj[:2] / pj[2]
        off = -pi[3] / pi[2] + pj[3] / pj[2]
        norm = float(np.hypot(*grad))
        for part in shapely.get_parts(shared):
            if part.geom_type != "LineString" or part.length < 0.25 * cell:
                continue
            steps = np.linspace(0.0, 1.0, max(3, int(part.length / cell) + 1))
            xy = shapely.get_coordinates(shapely.line_interpolate_point(part, steps, normalized=True))
            if (
                norm > 1e-6
                and float(np.max(np.abs(xy @ grad + off))) / norm <= near
                and _points_agree(
                    part, grid.xy, plab, labels[i], labels[j], grad, off, near, u.height(0.15)
                )
            ):
                key = (min(labels[i], labels[j]), max(labels[i], labels[j]))
                if key not in done:
                    done.add(key)
                    foot = centre - (float(grad @ centre) + off) / norm**2 * grad
                    t = np.array([-grad[1], grad[0]]) / norm
                    cuts.append(shapely.LineString([foot - reach * t, foot + reach * t]))
            else:
                cuts.append(_extend(part, cell))
    if not done:
        return regions
    noded = shapely.union_all([*cuts, fp.boundary])
    faces = [f for f in shapely.get_parts(shapely.polygonize(shapely.get_parts(noded))) if f.area > 0]
    faces = [f for f in faces if fp.contains(f.representative_point())]
    return _faces_by_label(faces, tree, polys, labels)


def _points_agree(part, xy, plab, li, lj, grad, off, near, tol) -> bool:
    """Whether the line ``grad . p + off = 0`` separates the points labelled li and lj
    near ``part`` (at most 10 % on the wrong side, ignoring points within ``tol`` in
    height of both planes)."""
    sel = (plab == li) | (plab == lj)
    if sel.sum() < 6:
        return True
    idx = np.flatnonzero(sel)
    idx = idx[shapely.contains_xy(part.buffer(near), xy[idx, 0], xy[idx, 1])]
    if len(idx) < 6:
        return True
    g = xy[idx] @ grad + off
    clear = np.abs(g) > tol
    if clear.sum() < 6:
        return True
    g, lab = g[clear], plab[idx][clear]
    wrong = 0
    for side in (g > 0, g <= 0):
        if side.any():
            counts = np.array([(lab[side] == li).sum(), (lab[side] == lj).sum()])
            wrong += int(counts.min())
    pos = lab[g > 0]
    neg = lab[g <= 0]
    if len(pos) and len(neg):
        major_pos = li if (pos == li).sum() >= (pos == lj).sum() else lj
        major_neg = li if (neg == li).sum() >= (neg == lj).sum() else lj
        if major_pos == major_neg:
            return False
    return wrong <= 0.1 * len(g)


def _extend(line: shapely.LineString, by: float) -> shapely.LineString:
    """A line with its first and last segments prolonged by ``by``."""
    c = shapely.get_coordinates(line)
    if len(c) < 2:
        return line
    d0, d1 = c[0] - c[1], c[-1] - c[-2]
    n0, n1 = np.linalg.norm(d0), np.linalg.norm(d1)
    if n0 > 0:
        c[0] = c[0] + d0 / n0 * by
    if n1 > 0:
        c[-1] = c[-1] + d1 / n1 * by
    return shapely.LineString(c)


def _lod13(grid: _Grid, fp, points, seg, g, u, cfg, *, labels=None) -> Solid:
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
        raise _LodFailure("no_roof_planes")
    # merge neighbouring labels closer than lod13_step (union-find over touching cells)
    sets = _MinRootSets(nl)
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
        raise _LodFailure("no_roof_planes")
    point_labels = np.where(lab >= 0, root[np.maximum(lab, 0)], -1)
    merged = _unpinch(merged, grid.inside)
    merged_grid = _Grid(merged, grid.inside, grid.transform, grid.cell, grid.xy, point_labels)
    return _roofed(merged_grid, fp, planes, g, u, intersect=False)[0]


def _height_levels(points: np.ndarray, cell: float, step: float) -> np.ndarray:
    """(n,) label of each roof point: the terraces of a roof cut at every ``step`` of
    height (connected ``cell`` cells whose highest points fall in one band)."""
    import affine

    from recon3d.buildings.detect import split_by_height
    from recon3d.terrain.dsm import grid_points

    x0, y1 = points[:, 0].min() - cell, points[:, 1].max() + cell
    shape = (int((y1 - points[:, 1].min()) / cell) + 2, int((points[:, 0].max() - x0) / cell) + 2)
    transform = affine.Affine(cell, 0.0, x0, 0.0, -cell, y1)
    top = grid_points(points, transform, shape, reducer="max")
    band = np.floor(top / step)
    labels, _ = split_by_height(band, np.isfinite(top), 0.5)  # neighbours join within one band
    col = ((points[:, 0] - x0) / cell).astype(np.int64)
    row = ((y1 - points[:, 1]) / cell).astype(np.int64)
    return labels[row, col].astype(np.int64) - 1


class _MinRootSets:
    """Union-find whose root is always the smallest member, so labels do not depend on merge order."""

    def __init__(self, n: int) -> None:
        self.parent = list(range(n))

    def find(self, a: int) -> int:
        while self.parent[a] != a:
            self.parent[a] = self.parent[self.parent[a]]
            a = self.parent[a]
        return a

    def union(self, a: int, b: int) -> int:
        """Join the sets of a and b; returns the root of the joined set."""
        ra, rb = self.find(a), self.find(b)
        root = min(ra, rb)
        self.parent[max(ra, rb)] = root
        return root


def _face_rings(verts: np.ndarray, edges: np.ndarray, normal: np.ndarray) -> list[list[np.ndarray]]:
    """Surfaces (outer ring + holes) of one planar face from its directed boundary edges.

    At a vertex with several outgoing edges the walk takes the one turning most
    sharply left, which splits a face pinched at a vertex into simple rings.
    """
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.5:
        e1 = np.cross(normal, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    uv = np.column_stack([verts @ e1, verts @ e2])
    outgoing: dict[int, list[int]] = {}
    for k, s in enumerate(edges[:, 0].tolist()):
        outgoing.setdefault(s, []).append(k)
    used = np.zeros(len(edges), bool)
    loops = []
    for start in range(len(edges)):
        if used[start]:
            continue
        ring = []
        k = start
        while not used[k]:
            used[k] = True
            s, t = int(edges[k, 0]), int(edges[k, 1])
            ring.append(s)
            options = [m for m in outgoing.get(t, []) if not used[m]]
            if not options:
                break
            if len(options) > 1:
                back = uv[s] - uv[t]
                best, pick = None, options[0]
                for m in options:
                    out = uv[int(edges[m, 1])] - uv[t]
                    # counter-clockwise angle from the outgoing edge to the way back
                    ang = _math.atan2(out[0] * back[1] - out[1] * back[0], out @ back) % (2 * _math.pi)
                    if best is None or ang < best:
                        best, pick = ang, m
                k = pick
            else:
                k = options[0]
        loops.append(np.array(ring, dtype=np.int64))
    outers, holes = [], []
    for ring in loops:
        p = uv[ring]
        area = 0.5 * float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
        (outers if area > 0 else holes).append((abs(area), ring))
    if not outers:
        raise _LodFailure("invalid_mesh", "a face has no outer ring")
    surfaces = [[ring] for _, ring in outers]
    if len(outers) == 1:
        surfaces[0] += [ring for _, ring in holes]
        return surfaces
    shapes = [shapely.Polygon(uv[ring]) for _, ring in outers]
    for _, ring in holes:
        probe = shapely.Polygon(uv[ring]).representative_point()
        inside = [k for k, s in enumerate(shapes) if s.covers(probe)]
        if not inside:
            inside = [int(np.argmin([s.distance(probe) for s in shapes]))]
        k = min(inside, key=lambda m: outers[m][0])
        surfaces[k].append(ring)
    return surfaces
