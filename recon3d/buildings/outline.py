"""Building outlines: raster contours, Douglas-Peucker, then regularisation.

A blob of nDSM cells gives a staircase outline along cell edges. It is simplified with
Douglas-Peucker (tolerance two cells, which flattens the staircase of an oblique wall
and the one-cell noise of a blob's border) and regularised the way photogrammetric
capture draws buildings:

1. the dominant orientation is the peak of a histogram of edge directions modulo 90
   degrees weighted by edge length (edges of a coarse, three-cell Douglas-Peucker
   outline), refined within 10 degrees by the projection-profile sharpness of the
   outline samples; when long edges remain off that orientation a second family is
   searched among them (a wing at an angle);
2. every edge becomes a line fitted (least squares, ends trimmed) to the outline
   samples between its two Douglas-Peucker vertices, which keeps sub-cell accuracy.
   Edges snap parallel or perpendicular to a family when within ``angle_tolerance``;
   a long edge only within what a cell of noise explains (a tapering wing keeps its
   taper), a short one (under three ``min_edge``) always. Consecutive free edges that
   turn by less than the tolerance become one;
3. bumps and notches shallower than the tolerance and shorter than three ``min_edge``
   are flattened; an oblique edge that only cuts a noisy corner goes;
4. consecutive parallel lines closer than ``min_edge`` merge, farther ones get a
   perpendicular connector (a step in the facade); edges shorter than ``min_edge`` are
   removed, shortest first, the neighbours meeting at the intersection of their lines;
   needles and spikes go;
5. the result must be a valid polygon close to the input (intersection over union at
   least 0.8, 95 % of each outline within ``max(3 cell, 2 min_edge, 2 tolerance)`` of
   the other); otherwise the Douglas-Peucker polygon is returned. Courtyards (holes)
   are regularised with the exterior's orientations.

Everything runs in coordinates relative to the outline's first vertex: line offsets of
national-grid coordinates would lose precision.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import rasterio.features
import shapely
from affine import Affine

log = logging.getLogger(__name__)

__all__ = ["douglas_peucker", "dominant_orientation", "raster_outline", "regularize", "remove_spikes"]


# --------------------------------------------------------------------------- contours


def raster_outline(mask: np.ndarray, transform: Affine, *, min_hole_area: float = 0.0) -> shapely.Polygon | None:
    """Outline of the cells of a mask along cell edges, the largest 4-connected part.

    Parameters
    ----------
    mask : (rows, cols) bool
    transform : affine.Affine
        Pixel-corner transform of ``mask``.
    min_hole_area : float
        Holes smaller than this (CRS units squared) are filled: gaps in the data
        (chimneys, dark roof patches), not courtyards.

    Returns
    -------
    shapely.Polygon or None
        Counter-clockwise exterior, clockwise holes; None for an empty mask.
    """
    mask = np.asarray(mask, bool)
    if not mask.any():
        return None
    best = None
    for geom, _ in rasterio.features.shapes(mask.astype(np.uint8), mask=mask, transform=transform, connectivity=4):
        poly = shapely.geometry.shape(geom)
        if best is None or poly.area > best.area:
            best = poly
    holes = [r for r in best.interiors if shapely.Polygon(r).area >= min_hole_area]
    return shapely.orient_polygons(shapely.Polygon(best.exterior, holes))


def douglas_peucker(ring: np.ndarray, tolerance: float) -> np.ndarray:
    """Indices of the vertices kept by Douglas-Peucker on a closed ring.

    The ring is cut at its vertex farthest from the first vertex and that farthest
    vertex, and both halves are simplified, so the result does not depend on where the
    ring starts as much as a naive open-polyline split would.

    Parameters
    ----------
    ring : (n, 2) float
        Ring vertices without the closing repeat.
    tolerance : float

    Returns
    -------
    (k,) int
        Sorted indices into ``ring`` (k >= 3 for a ring with an area, else all).
    """
    ring = np.asarray(ring, np.float64)
    n = len(ring)
    if n <= 3:
        return np.arange(n)
    a = int(np.argmax(np.hypot(*(ring - ring[0]).T)))
    b = int(np.argmax(np.hypot(*(ring - ring[a]).T)))
    a, b = min(a, b), max(a, b)
    if a == b:
        return np.arange(n)
    keep = np.zeros(n, bool)
    keep[[a, b]] = True
    closed = np.concatenate([ring, ring])
    stack = [(a, b), (b, a + n)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        p, q = closed[i], closed[j]
        seg = closed[i + 1 : j]
        d = q - p
        length = math.hypot(d[0], d[1])
        if length == 0:
            dist = np.hypot(*(seg - p).T)
        else:
            dist = np.abs(d[0] * (seg[:, 1] - p[1]) - d[1] * (seg[:, 0] - p[0])) / length
        k = int(np.argmax(dist))
        if dist[k] > tolerance:
            m = i + 1 + k
            keep[m % n] = True
            stack += [(i, m), (m, j)]
    return np.flatnonzero(keep)


def dominant_orientation(
    directions: np.ndarray, weights: np.ndarray, *, bin_deg: float = 1.0, smooth_deg: float = 3.0
) -> float:
    """Dominant orientation of edges modulo 90 degrees, in radians in [0, pi/2).

    A histogram of edge directions modulo 90 degrees weighted by length, smoothed
    circularly, gives the peak; the estimate is refined by the weighted circular mean of
    the directions within two smoothing widths of the peak.

    Parameters
    ----------
    directions : (m,) float
        Edge directions (radians, any range).
    weights : (m,) float
        Edge lengths.
    """
    directions = np.asarray(directions, np.float64)
    weights = np.asarray(weights, np.float64)
    if not len(directions) or weights.sum() <= 0:
        return 0.0
    mod = np.mod(directions, math.pi / 2)
    nbins = int(round(90.0 / bin_deg))
    hist = np.bincount(
        np.minimum((mod / (math.pi / 2) * nbins).astype(np.int64), nbins - 1), weights=weights, minlength=nbins
    )
    sigma = smooth_deg / bin_deg
    offsets = np.arange(-int(3 * sigma) - 1, int(3 * sigma) + 2)
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2)
    smoothed = sum(k * np.roll(hist, int(o)) for o, k in zip(offsets, kernel, strict=True))
    peak = (int(np.argmax(smoothed)) + 0.5) * math.pi / 2 / nbins
    diff = _wrap(mod - peak, math.pi / 2)
    near = np.abs(diff) <= math.radians(2 * smooth_deg)
    if near.any():
        peak += float(np.sum(diff[near] * weights[near]) / np.sum(weights[near]))
    return float(np.mod(peak, math.pi / 2))


def _wrap(angle: np.ndarray, period: float) -> np.ndarray:
    """Angles wrapped into [-period/2, period/2)."""
    return np.mod(np.asarray(angle) + period / 2, period) - period / 2


# --------------------------------------------------------------------------- regularisation


class _Line:
    """One edge of a ring: unit direction, normal offset and the samples it was fitted to."""

    __slots__ = ("c", "connector", "d", "normal", "pts", "snapped")

    def __init__(self, d: np.ndarray, pts: np.ndarray, snapped: bool, connector: bool = False) -> None:
        self.d = d / math.hypot(d[0], d[1])
        self.normal = np.array([-self.d[1], self.d[0]])
        self.pts = pts
        self.snapped = snapped
        self.connector = connector
        self.c = float(np.mean(pts @ self.normal))

    def weight(self) -> int:
        return len(self.pts)


def _trimmed(seg: np.ndarray) -> np.ndarray:
    """The samples of an edge without a tenth at each end (at least one): the rounded
    corners of a blob bend the ends of its edges."""
    k = max(1, len(seg) // 10)
    return seg[k:-k] if len(seg) > 2 * k + 2 else seg


def _principal_direction(seg: np.ndarray) -> np.ndarray:
    """Unit direction of the principal axis of (k, 2) samples, oriented from first to last."""
    d = seg[-1] - seg[0]
    seg = _trimmed(seg)
    if len(seg) >= 4:
        x, y = seg[:, 0] - seg[:, 0].mean(), seg[:, 1] - seg[:, 1].mean()
        t = 0.5 * math.atan2(2.0 * float(x @ y), float(x @ x - y @ y))
        v = np.array([math.cos(t), math.sin(t)])
        v = v if v @ d >= 0 else -v
        if v @ d > 0.9 * math.hypot(d[0], d[1]):
            return v
    return d / math.hypot(d[0], d[1])


def _edge_lines(
    pts: np.ndarray, idx: np.ndarray, families: list[float], angle_tol: float, free_min: float, cell: float
) -> list[_Line]:
    """Lines of the Douglas-Peucker edges of one ring, snapped to the orientation families.

    Edges within ``angle_tol`` of a family snap to it, long edges only within
    ``max(3 degrees, 4 atan(cell / length))``. Runs of consecutive edges that
    snap to no family and turn by less than ``angle_tol`` become one line (an oblique
    wall cut into pieces by noise). What is then still off every family and shorter than
    ``free_min`` snaps to the nearest family anyway (short oblique pieces of a noisy
    outline are noise, not walls); longer edges keep their fitted direction.
    """
    n = len(pts)
    segs = []
    for a, b in zip(idx, np.roll(idx, -1), strict=True):
        seg = pts[np.arange(a, b + (n if b <= a else 0) + 1) % n]
        if np.any(seg[-1] != seg[0]):
            segs.append(seg)
    fam = np.asarray(families)

    def delta(d: np.ndarray) -> np.ndarray:
        return _wrap(math.atan2(d[1], d[0]) - fam, math.pi / 2)

    dirs = [_principal_direction(seg) for seg in segs]
    free = [bool(np.min(np.abs(delta(d))) > angle_tol) for d in dirs]
    def length(seg: np.ndarray) -> float:
        return math.hypot(*(seg[-1] - seg[0]))

    merged = True
    while merged and len(segs) > 3:
        merged = False
        m = len(segs)
        for i in range(m):
            j, k = (i + 1) % m, (i + 2) % m
            if free[i] and free[j] and dirs[i] @ dirs[j] > math.cos(angle_tol):
                run = [i, j]
            elif free[i] and free[k] and length(segs[j]) < free_min and dirs[i] @ dirs[k] > math.cos(angle_tol):
                run = [i, j, k]  # a short noisy piece between two pieces of one oblique wall
            else:
                continue
            seg = np.concatenate([segs[run[0]], *(segs[r][1:] for r in run[1:])])
            d = _principal_direction(seg)
            segs[i], dirs[i], free[i] = seg, d, bool(np.min(np.abs(delta(d))) > angle_tol)
            for r in sorted(run[1:], reverse=True):
                del segs[r], dirs[r], free[r]
            merged = True
            break
    lines = []
    for seg, d in zip(segs, dirs, strict=True):
        dl = delta(d)
        best = int(np.argmin(np.abs(dl)))
        length = math.hypot(*(seg[-1] - seg[0]))
        # a long wall's direction is measured well: it snaps only when it deviates by
        # what a cell of noise explains (a tapering wing keeps its taper)
        tol = min(angle_tol, max(math.radians(3.0), 4.0 * math.atan2(cell, length)))
        snapped = abs(dl[best]) <= tol or length < free_min
        phi = math.atan2(d[1], d[0]) - (dl[best] if snapped else 0.0)
        lines.append(_Line(np.array([math.cos(phi), math.sin(phi)]), _trimmed(seg), snapped))
    return lines


def _parallel(a: _Line, b: _Line, tol: float = math.radians(3.0)) -> bool:
    return abs(float(a.d[0] * b.d[1] - a.d[1] * b.d[0])) < math.sin(tol)


def _merge(a: _Line, b: _Line) -> _Line:
    """One line from two parallel ones, direction of the longer, fitted to all samples."""
    d = a.d if a.weight() >= b.weight() else b.d
    return _Line(d, np.concatenate([a.pts, b.pts]), a.snapped or b.snapped)


def _offset(a: _Line, b: _Line) -> float:
    """Distance of the centre of ``b``'s samples from line ``a``."""
    return abs(float(a.normal @ b.pts.mean(axis=0)) - a.c)


def _connector(a: _Line, b: _Line) -> _Line:
    """A line perpendicular to parallel ``a`` and ``b`` through the point where they meet."""
    joint = 0.5 * (a.pts[-1] + b.pts[0])
    side = float(a.normal @ b.pts.mean(axis=0)) - a.c
    return _Line(a.normal * (1.0 if side >= 0 else -1.0), joint[None, :], a.snapped and b.snapped, connector=True)


def _resolve_parallels(lines: list[_Line], merge_dist: float) -> list[_Line]:
    """Merge consecutive parallel lines closer than ``merge_dist``; connect the others.

    Antiparallel neighbours (a needle) always merge.
    """
    changed = True
    while changed and len(lines) > 2:
        changed = False
        out: list[_Line] = []
        for cur in lines:
            if out and _parallel(out[-1], cur):
                prev = out[-1]
                if prev.d @ cur.d < 0 or _offset(prev, cur) < merge_dist:
                    out[-1] = _merge(prev, cur)
                    changed = True
                    continue
                out.append(_connector(prev, cur))
            out.append(cur)
        if len(out) > 2 and _parallel(out[-1], out[0]):
            last, first = out[-1], out[0]
            if last.d @ first.d < 0 or _offset(last, first) < merge_dist:
                out = [_merge(last, first), *out[1:-1]]
                changed = True
            else:
                out.append(_connector(last, first))
        lines = out
    return lines


def _corners(lines: list[_Line]) -> np.ndarray | None:
    """(m, 2) corners: corner i is where line i-1 meets line i; None if two neighbours are parallel."""
    corners = ring_corners(np.array([ln.normal for ln in lines]), np.array([ln.c for ln in lines]))
    return None if np.isnan(corners).any() else corners


def ring_corners(normal: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(m, 2) corners of a ring of lines ``x . normal[i] = c[i]``: corner i is where line
    i-1 meets line i, NaN where the two are parallel.

    Parameters
    ----------
    normal : (m, 2) float
        Unit normals of the lines, in ring order.
    c : (m,) float
        Their offsets from the origin along the normals.
    """
    n0, c0 = np.roll(normal, 1, axis=0), np.roll(c, 1)
    det = n0[:, 0] * normal[:, 1] - n0[:, 1] * normal[:, 0]
    det = np.where(np.abs(det) < 1e-9, np.nan, det)
    x = (c0 * normal[:, 1] - c * n0[:, 1]) / det
    y = (n0[:, 0] * c - normal[:, 0] * c0) / det
    return np.column_stack([x, y])


def _extent(line: _Line) -> float:
    """Length of a line's samples along its direction."""
    t = line.pts @ line.d
    return float(t.max() - t.min())


def _remove_bumps(lines: list[_Line], max_offset: float, max_length: float) -> list[_Line]:
    """Merge a line with the next-but-one or next-but-two when they are collinear.

    The one or two short lines between them (less than ``max_length`` long in all) form
    a bump or a notch shallower than ``max_offset``: noise of the blob's border, or a
    facade detail below what the cells can show.
    """
    changed = True
    while changed and len(lines) > 4:
        changed = False
        m = len(lines)
        for i in range(m):
            for span in (2, 3):
                k = (i + span) % m
                a, b = lines[i], lines[k]
                if k == i or a.d @ b.d < math.cos(math.radians(3.0)) or abs(a.c - b.c) >= max_offset:
                    continue
                between = [(i + j) % m for j in range(1, span)]
                if sum(_extent(lines[j]) for j in between) >= max_length:
                    continue
                lines[i] = _merge(a, b)
                for j in sorted([*between, k], reverse=True):
                    del lines[j]
                changed = True
                break
            if changed or len(lines) <= 4:
                break
    return lines


def _drop_false_chamfers(lines: list[_Line], tolerance: float) -> list[_Line]:
    """Remove oblique edges that only cut a noisy corner.

    Douglas-Peucker may cut a rounded, noisy corner with one oblique edge. When the two
    neighbours of an edge that snapped to no family meet at a corner that explains the
    edge's samples (90 % of them within ``tolerance`` of one of the two lines), the edge
    goes and the corner stays.
    """
    i = 0
    while i < len(lines) and len(lines) > 3:
        line = lines[i]
        a, b = lines[i - 1], lines[(i + 1) % len(lines)]
        if line.snapped or line.connector or _parallel(a, b):
            i += 1
            continue
        da = np.abs(line.pts @ a.normal - a.c)
        db = np.abs(line.pts @ b.normal - b.c)
        if np.percentile(np.minimum(da, db), 90) <= tolerance:
            del lines[i]
            continue
        i += 1
    return lines


def _drop_short(lines: list[_Line], min_edge: float, merge_dist: float) -> list[_Line] | None:
    """Remove edges shorter than ``min_edge`` (or reversed) until none is left; None if degenerate.

    The shortest edge goes first; its neighbours then meet at the intersection of their
    lines, or, when parallel, merge (a step below ``min_edge``) or get a perpendicular
    connector. A connector that comes out short or reversed makes its neighbours merge.
    """
    lines = _resolve_parallels(lines, merge_dist)
    for _ in range(4 * len(lines) + 8):
        if len(lines) < 3:
            return None
        corners = _corners(lines)
        if corners is None:
            return None
        nxt = np.roll(corners, -1, axis=0)
        lengths = np.einsum("ij,ij->i", nxt - corners, np.array([ln.d for ln in lines]))
        k = int(np.argmin(lengths))
        if lengths[k] >= min_edge or len(lines) <= 3:
            return lines if lengths.min() > 0 else None
        was_connector = lines[k].connector
        del lines[k]
        m = len(lines)
        if m < 3:
            return None
        a, b = (k - 1) % m, k % m
        if was_connector and _parallel(lines[a], lines[b]):
            merged = _merge(lines[a], lines[b])
            lines[a] = merged
            del lines[b]
        lines = _resolve_parallels(lines, max(merge_dist, min_edge))
    return None


def _remove_spikes(coords: np.ndarray, min_angle: float) -> np.ndarray:
    """Drop vertices whose interior angle is below ``min_angle`` (needles) or ~180 degrees."""
    for _ in range(len(coords)):
        if len(coords) < 4:
            return coords
        prev = np.roll(coords, 1, axis=0) - coords
        nxt = np.roll(coords, -1, axis=0) - coords
        lp, ln = np.hypot(*prev.T), np.hypot(*nxt.T)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.einsum("ij,ij->i", prev, nxt) / (lp * ln)
        cos = np.nan_to_num(cos, nan=1.0)
        bad = (cos > math.cos(min_angle)) | (cos < -math.cos(math.radians(1.0))) | (lp == 0)
        if not bad.any():
            return coords
        coords = np.delete(coords, int(np.argmax(bad)), axis=0)
    return coords


def remove_spikes(polygon: shapely.Polygon, min_angle: float = 1.0) -> shapely.Polygon | None:
    """The polygon without needles: vertices of every ring whose interior angle is
    below ``min_angle`` degrees, collinear vertices and repeated vertices are dropped.

    Cutting a block into buildings can leave zero-width spikes (a part's outline runs
    out along a cut and back); their edges would be shared by four faces of a solid.
    None when no polygon with an area is left.
    """
    angle = math.radians(min_angle)
    rings = [_remove_spikes(np.asarray(r.coords)[:-1, :2], angle) for r in (polygon.exterior, *polygon.interiors)]
    if len(rings[0]) < 3:
        return None
    holes = [r for r in rings[1:] if len(r) >= 3]
    return _valid_polygon(shapely.Polygon(rings[0], holes))


def _samples(ring: shapely.LinearRing, cell: float) -> np.ndarray:
    """(n, 2) samples along a ring, at most one cell apart (closing repeat dropped)."""
    return np.asarray(shapely.segmentize(ring, cell).coords)[:-1, :2]


def _regular_ring(
    pts: np.ndarray,
    families: list[float],
    *,
    cell: float,
    tolerance: float,
    min_edge: float,
    angle_tol: float,
) -> np.ndarray | None:
    """Regularised corners of one ring given by (n, 2) samples, None when it degenerates."""
    if len(pts) < 3:
        return None
    idx = douglas_peucker(pts, tolerance)
    if len(idx) < 3:
        return None
    free_min = max(3.0 * min_edge, 4.0 * cell)
    lines = _edge_lines(pts, idx, families, angle_tol, free_min=free_min, cell=cell)
    lines = _remove_bumps(lines, max_offset=tolerance, max_length=free_min)
    lines = _drop_false_chamfers(lines, tolerance)
    lines = _drop_short(lines, min_edge, merge_dist=min(cell, min_edge))
    if lines is None:
        return None
    coords = _corners(lines)
    if coords is None:
        return None
    return _remove_spikes(coords, math.radians(12.0))


def _profile_sharpness(pts: np.ndarray, thetas: np.ndarray, bin_size: float) -> np.ndarray:
    """(k,) sum of squared counts of the outline samples projected on both axes at each angle.

    Walls parallel to the axes collapse into few bins, so the score peaks at the
    building's orientation (the projection-profile criterion of document deskewing).
    """
    centred = pts - pts.mean(axis=0)
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    out = np.zeros(len(thetas))
    k = len(thetas)
    for w in (centred[:, 0] * c + centred[:, 1] * s, centred[:, 1] * c - centred[:, 0] * s):
        # linear binning (each sample split between its two nearest bins) keeps the
        # score continuous in the angle, so an exact rectangle peaks exactly
        f = (w - w.min(axis=1, keepdims=True)) / bin_size
        b = np.floor(f).astype(np.int64)
        frac = f - b
        width = int(b.max()) + 2
        base = (b + np.arange(k)[:, None] * width).ravel()
        h = np.bincount(base, weights=(1.0 - frac).ravel(), minlength=k * width)
        h += np.bincount(base + 1, weights=frac.ravel(), minlength=k * width)
        h = h.reshape(k, width)
        out += np.einsum("ij,ij->i", h, h)
    return out


def _families(pts: np.ndarray, cell: float, angle_tol: float) -> list[float]:
    """Up to two dominant orientations of a densely sampled ring.

    The first comes from the length-weighted histogram of the edges of a coarse
    Douglas-Peucker outline (3 cells, so the staircase and the noise of the blob's
    border are gone), refined within 10 degrees by the projection-profile sharpness of
    all samples. A second family is searched among edges off the first one when they
    make more than a quarter of the outline.
    """
    idx = douglas_peucker(pts, 3.0 * cell)
    v = pts[np.roll(idx, -1)] - pts[idx]
    length = np.hypot(*v.T)
    phi = np.arctan2(v[:, 1], v[:, 0])
    theta = dominant_orientation(phi, length)
    for span, step in ((math.radians(10.0), math.radians(0.5)), (math.radians(0.5), math.radians(0.1))):
        cand = theta + np.arange(-span, span + step / 2, step)
        theta = float(cand[np.argmax(_profile_sharpness(pts, cand, cell / 2))])
    theta = float(np.mod(theta, math.pi / 2))
    families = [theta]
    off = np.abs(_wrap(phi - theta, math.pi / 2)) > angle_tol
    if off.any() and length[off].sum() > 0.25 * length.sum():
        families.append(dominant_orientation(phi[off], length[off]))
    return families


def _similar(a: shapely.Polygon, b: shapely.Polygon, max_distance: float, min_iou: float) -> bool:
    """Intersection over union at least ``min_iou``, and 95 % of each outline within
    ``max_distance`` of the other (a robust Hausdorff distance: a thin protrusion the
    regularisation rightly drops does not count, a corner gone astray does)."""
    inter = a.intersection(b).area
    union = a.area + b.area - inter
    if union <= 0 or inter / union < min_iou:
        return False
    step = max_distance / 4
    for p, q in ((a, b), (b, a)):
        samples = shapely.points(np.asarray(shapely.segmentize(p.exterior, step).coords))
        if np.percentile(shapely.distance(samples, q.exterior), 95) > max_distance:
            return False
    return True


def _valid_polygon(geom) -> shapely.Polygon | None:
    """The largest polygon of a geometry after repair, None when nothing has an area."""
    if geom is None or geom.is_empty:
        return None
    if not geom.is_valid:
        geom = shapely.make_valid(geom)
    parts = [g for g in getattr(geom, "geoms", [geom]) if g.geom_type == "Polygon" and g.area > 0]
    parts += [q for g in getattr(geom, "geoms", []) if g.geom_type == "MultiPolygon" for q in g.geoms]
    if not parts:
        return None
    return max(parts, key=lambda p: p.area)


def regularize(
    polygon: shapely.Polygon,
    *,
    cell: float,
    min_edge: float,
    tolerance: float | None = None,
    angle_tolerance: float = 15.0,
    min_hole_area: float = 0.0,
) -> shapely.Polygon:
    """Regularised building outline: dominant directions, straight edges, clean corners.

    Parameters
    ----------
    polygon : shapely.Polygon
        A raw outline, typically cell edges of an nDSM blob (see :func:`raster_outline`).
        An invalid polygon is repaired first (its largest part is used).
    cell : float
        Cell size of the raster the outline comes from (CRS units); sets the sampling
        of the outline and the default Douglas-Peucker tolerance.
    min_edge : float
        Shortest edge kept (CRS units).
    tolerance : float, optional
        Douglas-Peucker tolerance; ``2 * cell`` by default, which flattens the
        staircase of an oblique wall and the one-cell noise of a blob's border (the
        lines are then fitted to all samples, so accuracy stays sub-cell).
    angle_tolerance : float
        Degrees within which an edge snaps to a dominant orientation.
    min_hole_area : float
        Holes (courtyards) smaller than this are dropped.

    Returns
    -------
    shapely.Polygon
        Valid, non-empty, counter-clockwise exterior. When regularisation fails or moves
        the outline too far (intersection over union below 0.8, or a Hausdorff distance
        above ``max(3 cell, 2 min_edge, 2 tolerance)``), the Douglas-Peucker polygon at
        ``tolerance``, else at half a cell.

    Raises
    ------
    ValueError
        When the input has no area at all.
    """
    poly = _valid_polygon(polygon)
    if poly is None:
        raise ValueError("cannot regularise an empty polygon or one without area")
    poly = shapely.Polygon(poly.exterior, [r for r in poly.interiors if shapely.Polygon(r).area >= max(min_hole_area, 0)])
    # work near the origin: line offsets of national-grid coordinates lose precision
    origin = np.asarray(poly.exterior.coords[0][:2])
    poly = shapely.transform(poly, lambda xy: xy - origin)
    tolerance = 2.0 * cell if tolerance is None else tolerance
    angle_tol = math.radians(angle_tolerance)
    dense = _samples(poly.exterior, cell)
    families = _families(dense, cell, angle_tol)
    kw = dict(cell=cell, tolerance=tolerance, min_edge=min_edge, angle_tol=angle_tol)
    shell = _regular_ring(dense, families, **kw)
    result = None
    if shell is not None and len(shell) >= 3:
        outer = shapely.Polygon(shell)
        if not outer.is_valid:  # a small loop where two corners crossed: keep the main part
            fixed = _valid_polygon(outer)
            outer = fixed if fixed is not None and fixed.area >= 0.95 * abs(shapely.area(outer)) else outer
            if outer.is_valid:
                outer = shapely.Polygon(_remove_spikes(np.asarray(outer.exterior.coords)[:-1], math.radians(12.0)))
        if outer.is_valid and outer.area > 0:
            holes = []
            for r in poly.interiors:
                h = _regular_ring(_samples(r, cell), families, **kw)
                hp = shapely.Polygon(h) if h is not None and len(h) >= 3 else None
                if hp is None or not hp.is_valid or hp.area < min_hole_area:
                    hp = _valid_polygon(shapely.Polygon(r).simplify(tolerance))
                if hp is not None and outer.contains(hp) and not any(hp.intersects(o) for o in holes):
                    holes.append(hp)
            candidate = shapely.Polygon(outer.exterior, [np.asarray(h.exterior.coords) for h in holes])
            if not candidate.is_valid:
                candidate = outer
            if candidate.is_valid and candidate.area > 0:
                result = candidate
    tol_dist = max(3.0 * cell, 2.0 * min_edge, 2.0 * tolerance)
    # compare with the staircase flattened to half a cell: the same shape, far fewer vertices
    target = _valid_polygon(poly.simplify(cell / 2, preserve_topology=True)) or poly
    if result is None or not _similar(result, target, tol_dist, 0.8):
        log.debug("regularisation failed or moved the outline too much; keeping the simplified outline")
        simple = _valid_polygon(poly.simplify(tolerance, preserve_topology=True))
        result = simple if simple is not None and _similar(simple, target, tol_dist, 0.8) else target
    result = shapely.orient_polygons(result)
    if not result.is_valid or result.is_empty:
        result = shapely.orient_polygons(poly)
    return shapely.transform(result, lambda xy: xy + origin)
