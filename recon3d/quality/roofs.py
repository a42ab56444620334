"""Roof accuracy: point-to-roof distances, roof planes against a reference model.

Definitions (following the ISPRS urban classification and 3-D reconstruction
benchmark, Rottensteiner et al. 2014, so numbers can be compared):

- **point-to-roof distance**: vertical distance ``z_point - z_roof(x, y)`` from a
  point to the highest roof surface of a solid above the point's (x, y); points
  outside the roof's plan view get NaN. ``roof_rms`` is its RMS; with ``outlier``
  the points further off than that (chimneys, antennas, overhanging trees, wall
  points) are left out and their share reported by :func:`roof_residuals_summary`.
- **roof plane**: the roof surfaces of a solid grouped by plane (normals within
  ``angle`` degrees and offsets within ``offset``), whether they touch or not, with
  their union in plan view. A reconstructed and a reference plane **correspond**
  when their normals differ by at most ``max_angle`` degrees, their heights differ
  by at most ``max_dz`` on average over their common plan area (the difference at
  the overlap's centroid, the planes being linear) and their plan views overlap by
  at least ``min_overlap`` (50 %) of the area of the plane being judged.
  **Completeness** is the share of reference planes that have a
  corresponding reconstructed plane (overlap >= 50 % of the *reference* plane's
  area), **correctness** the share of reconstructed planes that have a
  corresponding reference plane (overlap >= 50 % of the *reconstructed* plane's
  area). Planes smaller than ``min_area`` in plan view are not counted on either
  side (they are too small to be supported by points at the density compared).
- **roof height RMS** between two models (ISPRS RMS_Z): over a regular grid of
  (x, y), the RMS of the difference of the two roofs' heights at the points where
  a reference plane and its corresponding model plane (largest overlap among the
  planes of similar orientation) both lie, so that a misplaced step edge counts
  in the plan-view accuracy, not in the height accuracy. ``height_rms_all`` takes
  every point inside both roofs instead, and ``misplaced_share`` is the share of
  those points whose heights differ by more than 0.5 m (mostly along step edges).
- **volume error**: (V_model - V_reference) / V_reference.
- **unmodelled roof part**: a connected group of a building's roof points more than
  1 m above or below its best solid's roof, of 2 m2 and more (a dormer, a stair
  house, a light well the model left out); :func:`unmodelled_roof_parts` finds them,
  :func:`fit_quality` reports their count and area per building.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from recon3d.core.city import Building, Solid
from recon3d.core.geo import LocalFrame, Units

__all__ = [
    "RoofPlaneView",
    "compare_roof_planes",
    "compare_roofs",
    "fit_quality",
    "point_to_roof",
    "roof_height_at",
    "roof_planes",
    "roof_residuals_summary",
    "roof_rms",
    "solid_volume",
    "unmodelled_roof_parts",
]


@dataclass
class RoofPlaneView:
    """One roof plane of a model: its plane, plan-view shape and area.

    Attributes
    ----------
    normal : (3,) float
        Unit normal pointing up.
    offset : float
        ``d`` of ``n . x + d = 0``.
    footprint : shapely geometry
        Union of the plane's surfaces projected on (x, y).
    area : float
        Plan-view area.
    surfaces : list of int
        Indices of the solid's surfaces on this plane.
    """

    normal: np.ndarray
    offset: float
    footprint: object
    area: float
    surfaces: list[int]


def _roof_triangles(solid: Solid) -> np.ndarray:
    """(m, 3, 3) roof triangles of a solid."""
    vertices, faces, surface = solid.mesh()
    roof = np.asarray(solid.semantics)[surface] == "RoofSurface" if len(surface) else np.zeros(0, bool)
    return vertices[faces[roof]]


def roof_height_at(solid: Solid, xy: np.ndarray) -> np.ndarray:
    """Height of the highest roof surface above each (x, y); NaN where there is none.

    Parameters
    ----------
    solid : Solid
        Any solid or multi-surface with RoofSurface semantics.
    xy : (n, 2) float
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(xy), np.nan)
    tri = _roof_triangles(solid)
    if not len(tri) or not len(xy):
        return out
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = np.abs(det) > 1e-12
    tri, a, b, c, det = tri[ok], a[ok], b[ok], c[ok], det[ok]
    polys = shapely.polygons(tri[:, :, :2])
    tree = shapely.STRtree(polys)
    pi, ti = tree.query(shapely.points(xy), predicate="intersects")
    if not len(pi):
        return out
    p = xy[pi]
    pa, pb, pc = a[ti, :2] - p, b[ti, :2] - p, c[ti, :2] - p
    l1 = (pb[:, 0] * pc[:, 1] - pc[:, 0] * pb[:, 1]) / det[ti]
    l2 = (pc[:, 0] * pa[:, 1] - pa[:, 0] * pc[:, 1]) / det[ti]
    l3 = 1.0 - l1 - l2
    z = l1 * a[ti, 2] + l2 * b[ti, 2] + l3 * c[ti, 2]
    np.fmax.at(out, pi, z)
    return out


def point_to_roof(solid: Solid, points: np.ndarray) -> np.ndarray:
    """Vertical distances ``z - z_roof(x, y)`` of points to a solid's roof (NaN outside it)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return pts[:, 2] - roof_height_at(solid, pts[:, :2])


def roof_rms(solid: Solid, points: np.ndarray, *, outlier: float | None = None) -> float:
    """RMS of the point-to-roof distances (points above the roof only).

    Parameters
    ----------
    outlier : float, optional
        Points further than this from the roof are left out (robust RMS).

    Returns
    -------
    float
        NaN when no point lies above the roof.
    """
    r = point_to_roof(solid, points)
    r = r[np.isfinite(r)]
    if outlier is not None:
        r = r[np.abs(r) <= outlier]
    return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")


def roof_residuals_summary(solid: Solid, points: np.ndarray, *, outlier: float = 1.0) -> dict:
    """n, RMS (all and without outliers), mean, NMAD and outlier share of point-to-roof distances."""
    return _residuals_summary(point_to_roof(solid, points), outlier)


def _residuals_summary(r: np.ndarray, outlier: float) -> dict:
    """:func:`roof_residuals_summary` of given point-to-roof distances (NaN: outside the roof)."""
    r = r[np.isfinite(r)]
    if not len(r):
        return {"n": 0}
    inl = r[np.abs(r) <= outlier]
    return {
        "n": int(len(r)),
        "rms": float(np.sqrt(np.mean(r**2))),
        "rms_robust": float(np.sqrt(np.mean(inl**2))) if len(inl) else float("nan"),
        "mean": float(np.mean(r)),
        "nmad": float(1.4826 * np.median(np.abs(r - np.median(r)))),
        "outlier_share": float(1.0 - len(inl) / len(r)),
        "outlier_threshold": float(outlier),
    }


def roof_planes(solid: Solid, *, angle: float = 3.0, offset: float = 0.1) -> list[RoofPlaneView]:
    """The roof surfaces of a solid grouped by plane (see the module docstring)."""
    from recon3d.core.city import newell_normal

    items = []
    for i, (rings, kind) in enumerate(zip(solid.surfaces, solid.semantics, strict=True)):
        if kind != "RoofSurface":
            continue
        pts = solid.vertices[rings[0]]
        n = newell_normal(pts)
        norm = np.linalg.norm(n)
        if norm <= 0:
            continue
        n = n / norm
        if n[2] < 0:
            n = -n
        d = -float(np.mean(solid.vertices[np.concatenate(rings)] @ n))
        shape = shapely.Polygon(pts[:, :2], [solid.vertices[r][:, :2] for r in rings[1:]])
        shape = shapely.make_valid(shape) if not shape.is_valid else shape
        items.append((i, n, d, shape, 0.5 * norm))
    cos_a = math.cos(math.radians(angle))
    groups: list[list] = []
    for i, n, d, shape, area in sorted(items, key=lambda t: -t[4]):
        for grp in groups:
            gn, gd = grp[0][1], grp[0][2]
            centre = np.asarray(shape.representative_point().coords)[0] if not shape.is_empty else None
            if float(n @ gn) >= cos_a and centre is not None:
                # compare the offsets at the surface's own location
                z_here = -(gn[0] * centre[0] + gn[1] * centre[1] + gd) / gn[2]
                z_own = -(n[0] * centre[0] + n[1] * centre[1] + d) / n[2]
                if abs(z_here - z_own) <= offset:
                    grp.append((i, n, d, shape, area))
                    break
        else:
            groups.append([(i, n, d, shape, area)])
    out = []
    for grp in groups:
        weights = np.array([g[4] for g in grp])
        n = np.average([g[1] for g in grp], axis=0, weights=weights)
        n /= np.linalg.norm(n)
        d = float(np.average([g[2] for g in grp], weights=weights))
        shape = shapely.union_all([g[3] for g in grp])
        out.append(RoofPlaneView(n, d, shape, float(shape.area), [g[0] for g in grp]))
    return out


def compare_roof_planes(
    reference: list[RoofPlaneView],
    model: list[RoofPlaneView],
    *,
    min_overlap: float = 0.5,
    max_angle: float = 10.0,
    min_area: float = 0.0,
    max_dz: float = 0.5,
) -> dict:
    """Roof-plane completeness and correctness (see the module docstring).

    Returns
    -------
    dict
        ``completeness``, ``correctness`` (NaN when nothing to count), the counts
        ``n_reference``, ``n_model``, ``n_found``, ``n_correct``, and the parameters.
    """
    ref = [p for p in reference if p.area >= min_area]
    mod = [p for p in model if p.area >= min_area]
    cos_a = math.cos(math.radians(max_angle))
    overlap = np.zeros((len(ref), len(mod)))
    for i, r in enumerate(ref):
        for j, m in enumerate(mod):
            if float(r.normal @ m.normal) >= cos_a:
                common = shapely.intersection(r.footprint, m.footprint)
                if common.is_empty or common.area <= 0:
                    continue
                c = np.asarray(common.centroid.coords)[0]
                if abs(_plane_z(r, c) - _plane_z(m, c)) <= max_dz:
                    overlap[i, j] = common.area
    ref_area = np.array([p.area for p in ref])
    mod_area = np.array([p.area for p in mod])
    found = np.zeros(len(ref), bool)
    correct = np.zeros(len(mod), bool)
    if len(ref) and len(mod):
        found = (overlap >= min_overlap * ref_area[:, None]).any(axis=1)
        correct = (overlap >= min_overlap * mod_area[None, :]).any(axis=0)
    return {
        "completeness": float(found.mean()) if len(ref) else float("nan"),
        "correctness": float(correct.mean()) if len(mod) else float("nan"),
        "n_reference": len(ref),
        "n_model": len(mod),
        "n_found": int(found.sum()),
        "n_correct": int(correct.sum()),
        "min_overlap": min_overlap,
        "max_angle": max_angle,
        "min_area": min_area,
        "max_dz": max_dz,
    }


def _plane_z(plane: RoofPlaneView, xy: np.ndarray) -> float:
    n = plane.normal
    return float(-(n[0] * xy[0] + n[1] * xy[1] + plane.offset) / n[2])


def solid_volume(solid: Solid) -> float:
    """Volume enclosed by a closed solid (divergence theorem on its triangulation)."""
    vertices, faces, _ = solid.mesh()
    if not len(faces):
        return 0.0
    v = vertices - vertices.mean(axis=0)
    a, b, c = (v[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c))) / 6.0


def compare_roofs(
    reference: Solid,
    model: Solid,
    *,
    step: float = 0.25,
    min_overlap: float = 0.5,
    max_angle: float = 10.0,
    min_area: float = 0.0,
    max_dz: float = 0.5,
    volume: bool = True,
) -> dict:
    """Roof height RMS, roof-plane completeness/correctness and volume error of a model
    against a reference model of the same building (same coordinates).

    Parameters
    ----------
    step : float
        Grid spacing of the height comparison.
    volume : bool
        Also compare volumes (both must be closed solids).
    """
    ref_planes = roof_planes(reference)
    mod_planes = roof_planes(model)
    out = compare_roof_planes(
        ref_planes, mod_planes,
        min_overlap=min_overlap, max_angle=max_angle, min_area=min_area, max_dz=max_dz,
    )
    plan = shapely.intersection(
        shapely.union_all([p.footprint for p in ref_planes]),
        shapely.union_all([p.footprint for p in mod_planes]),
    )
    nan = float("nan")
    out.update(height_rms=nan, height_rms_all=nan, misplaced_share=nan, height_n=0)
    if not plan.is_empty:
        x0, y0, x1, y1 = plan.bounds
        gx, gy = np.meshgrid(np.arange(x0 + step / 2, x1, step), np.arange(y0 + step / 2, y1, step))
        xy = np.column_stack([gx.ravel(), gy.ravel()])
        xy = xy[shapely.contains_xy(plan, xy[:, 0], xy[:, 1])]
        dz = roof_height_at(model, xy) - roof_height_at(reference, xy)
        ok = np.isfinite(dz)
        if ok.any():
            out["height_rms_all"] = float(np.sqrt(np.mean(dz[ok] ** 2)))
            out["misplaced_share"] = float(np.mean(np.abs(dz[ok]) > 0.5))
        # corresponding planes: for each reference plane, the model plane of similar
        # orientation overlapping it most
        cos_a = math.cos(math.radians(max_angle))
        matched = np.zeros(len(xy), bool)
        for r in ref_planes:
            best, area = None, 0.0
            for m in mod_planes:
                if float(r.normal @ m.normal) >= cos_a:
                    common = shapely.intersection(r.footprint, m.footprint)
                    if common.is_empty or common.area <= area:
                        continue
                    c = np.asarray(common.centroid.coords)[0]
                    if abs(_plane_z(r, c) - _plane_z(m, c)) <= max_dz:
                        best, area = m, common.area
            if best is not None:
                both = shapely.intersection(r.footprint, best.footprint)
                matched |= shapely.contains_xy(both, xy[:, 0], xy[:, 1])
        sel = ok & matched
        if sel.any():
            out["height_rms"] = float(np.sqrt(np.mean(dz[sel] ** 2)))
            out["height_n"] = int(sel.sum())
    if volume:
        vr, vm = solid_volume(reference), solid_volume(model)
        out["volume_reference"] = vr
        out["volume_model"] = vm
        out["volume_error"] = (vm - vr) / vr if vr > 0 else float("nan")
    return out


def fit_quality(b: Building, points: np.ndarray, frame: LocalFrame, u: Units) -> dict:
    """How well a building's solids explain its points, as roofer reports it: its roof point density,
    the RMS of its roof points to each LoD's roof (``roof_point_rms_lod22_m`` ..., all
    points, vertical distances) and the share of them more than 1 m from the best one.

    ``points`` are the non-ground, non-vegetation points of the footprint's bounding
    box, (n, 3) world coordinates; those inside the footprint and above its lower part
    (as :func:`~recon3d.buildings.lod.build_lods` takes them) are its roof points."""
    out: dict = {}
    if b.footprint is not None and len(points):
        inside = points[shapely.contains_xy(b.footprint, points[:, 0], points[:, 1])]
        if np.isfinite(b.ground_z) and np.isfinite(b.roof_z):  # roof points as build_lods takes them
            inside = inside[inside[:, 2] > b.ground_z + min(u.height(1.0), 0.5 * (b.roof_z - b.ground_z))]
        area = b.footprint.area
        out["roof_points_per_m2"] = round(len(inside) / (area * u.horizontal**2) if area > 0 else 0.0, 2)
        if b.solids and len(inside):
            local = frame.to_local(inside)
            dz = {lod: point_to_roof(solid, local) for lod, solid in b.solids.items()}
            fits = {lod: _residuals_summary(r, u.height(1.0)) for lod, r in dz.items()}
            fits = {lod: f for lod, f in sorted(fits.items(), key=lambda kv: float(kv[0])) if f.get("n")}
            for lod, f in fits.items():
                out[f"roof_point_rms_{lod_key(lod)}_m"] = round(float(f["rms"]) * u.vertical, 3)
            best = max(b.solids, key=float)
            if best in fits:
                out["roof_points_off_1m_share"] = round(float(fits[best]["outlier_share"]), 3)
                missed = unmodelled_roof_parts(dz[best], local, b.footprint, frame, u)
                out["roof_unmodelled_parts"] = len(missed)
                out["roof_unmodelled_area_m2"] = round(float(sum(missed)), 1)
    return out


def unmodelled_roof_parts(
    dz: np.ndarray,
    local: np.ndarray,
    footprint: shapely.Polygon,
    frame: LocalFrame,
    u: Units,
    *,
    off: float = 1.0,
    min_area: float = 2.0,
) -> list[float]:
    """Areas (m2) of the roof parts a solid misses: connected groups of roof points
    more than ``off`` metres above or below its roof (``dz``, from
    :func:`point_to_roof`), of ``min_area`` and more
    (dormers, stair houses, light wells, roof parts left out).

    Points within 1 m of the outline are left out (wall points lie there). A group's
    area is its point count over the roof's point density, so it needs no guess of
    the sampling; points are grouped on a grid of 1.5 times their mean spacing (at
    least 0.5 m), its 8-connected occupied cells.

    Parameters
    ----------
    dz : (n,) float
        Vertical distances of the roof points to the building's best solid (NaN
        outside its roof: not counted).
    local : (n, 3) float
        The roof points, local coordinates.
    footprint : shapely.Polygon
        World outline.
    frame : LocalFrame
    u : Units
    off, min_area : float
        Metres and square metres.

    Returns
    -------
    list of float
        Largest first; empty when the solid explains every part.
    """
    from scipy import ndimage

    inner = footprint.buffer(-u.length(1.0))
    if inner.is_empty or not len(local):
        return []
    world = frame.to_world(local)
    keep = shapely.contains_xy(inner, world[:, 0], world[:, 1])
    density = keep.sum() / (inner.area * u.horizontal**2)  # points per m2
    far = keep & (np.abs(np.nan_to_num(dz, nan=0.0)) > u.height(off))
    if density <= 0 or far.sum() < min_area * density:
        return []
    cell = u.length(max(0.5, 1.5 / np.sqrt(density)))
    ij = np.floor((local[far, :2] - local[far, :2].min(axis=0)) / cell).astype(np.int64)
    grid = np.zeros(tuple(ij.max(axis=0) + 1), bool)
    grid[ij[:, 0], ij[:, 1]] = True
    labels, _ = ndimage.label(grid, structure=np.ones((3, 3), bool))
    counts = np.bincount(labels[ij[:, 0], ij[:, 1]])[1:]
    areas = np.sort(counts / density)[::-1]
    return [float(a) for a in areas if a >= min_area]


def lod_key(lod: str) -> str:
    """The attribute suffix of a LoD: "2.2" -> "lod22" (``roof_point_rms_lod22_m``, ``validity_lod22``)."""
    return "lod" + lod.replace(".", "")


def validity_attributes(validity: dict) -> dict:
    """``validity_lod1`` / ``validity_lod13`` / ``validity_lod22`` attributes from
    :attr:`~recon3d.buildings.lod.LodResult.validity`: "valid", or the val3dity codes and
    names of the check that failed the LoD, e.g. "203 NON_PLANAR_POLYGON_DISTANCE_PLANE"."""
    from recon3d.quality.meshcheck import ISSUE_NAMES

    return {
        f"validity_{lod_key(lod)}": "; ".join(f"{c} {ISSUE_NAMES.get(c, 'UNKNOWN')}" for c in codes) or "valid"
        for lod, codes in validity.items()
    }
