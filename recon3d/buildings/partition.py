"""The planar partition of a footprint into roof parts, from the roof label grid.

The grid's regions are polygonized, their shared edges straightened onto the lines
between the points of either side, clipped by the exact footprint, cut along the
intersection lines of neighbouring planes (ridges, hips, valleys), cleared of slivers
and opened where a part touches itself at a vertex. :mod:`recon3d.buildings.extrude`
builds the solid over the result. Local coordinates.
"""

from __future__ import annotations

import numpy as np
import shapely

from recon3d.buildings.roofgrid import RoofGrid

__all__ = ["absorb_small", "arrangement", "drop_close", "grid_regions", "necks", "open_crossings", "open_pinches",
           "partition_rms", "refit_parts"]


def grid_regions(grid: RoofGrid, fp) -> list[tuple[shapely.Polygon, int]]:
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
    face_array = np.array(faces, dtype=object)
    face_of, cand = tree.query(face_array)  # by face, each face's candidates in tree order
    if len(cand):
        areas = shapely.area(shapely.intersection(face_array[face_of], np.array(geoms, dtype=object)[cand]))
        start = np.flatnonzero(np.r_[True, face_of[1:] != face_of[:-1]])
        count = np.diff(np.r_[start, len(cand)])
        largest = areas == np.repeat(np.maximum.reduceat(areas, start), count)
        best = np.minimum.reduceat(np.where(largest, np.arange(len(cand)), len(cand)), start)  # the first of equals
        for f, c in zip(face_of[start].tolist(), cand[best].tolist(), strict=True):
            by_label.setdefault(values[c], []).append(faces[f])
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
    if not diff.any():  # labels apart from each other by more than the reach
        return {}
    pairs, la, lb = pairs[diff], la[diff], lb[diff]
    mid = 0.5 * (pts[pairs[:, 0]] + pts[pairs[:, 1]])
    span = int(lab.max()) + 1
    key = np.minimum(la, lb) * span + np.maximum(la, lb)
    order = np.argsort(key, kind="stable")  # by pair, each pair's midpoints in their order
    keys, start = np.unique(key[order], return_index=True)
    groups = np.split(mid[order], start[1:])
    return {(int(k // span), int(k % span)): g for k, g in zip(keys.tolist(), groups, strict=True)}


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
    on_rim = ~(shapely.distance(shapely.points(c[[0, -1]]), rim) > 1e-9 * max(1.0, cell))
    for end, seg, slides in ((0, 0, on_rim[0]), (len(c) - 1, len(seg_a) - 1, on_rim[1])):
        if not slides:
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


def absorb_small(parts, min_area, min_width=0.0):
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


def refit_parts(regions, planes, points: np.ndarray, off: float, min_points: int = 10):
    """Each part with the plane its own points lie on.

    A part keeps its plane unless most of the points inside it lie more than ``off``
    above or below it (a speck of a lower roof's label left on a higher roof by the
    label grid's fills and filters) and another plane explains them: then it takes the
    plane with the smallest median vertical distance to them, if that is under
    ``off / 2``. Parts with fewer than ``min_points`` points keep theirs.

    Parameters
    ----------
    regions : list of (shapely.Polygon, int)
    planes : list of (4,) float
    points : (n, 3) float
        The roof points (the regions' coordinates).
    off : float
        Vertical distance beyond which a point is off a plane.
    """
    if len(regions) < 2 or len(planes) < 2 or not len(points):
        return regions
    plane = np.asarray(planes, dtype=np.float64)
    pi, ri = shapely.STRtree([p for p, _ in regions]).query(shapely.points(points[:, :2]), predicate="intersects")
    out = []
    for j, (poly, label) in enumerate(regions):
        own = points[pi[ri == j]]
        if len(own) >= min_points:
            heights = -(own[:, :1] * plane[:, 0] + own[:, 1:2] * plane[:, 1] + plane[:, 3]) / plane[:, 2]
            dz = np.abs(own[:, 2:3] - heights)  # (points, planes)
            best = int(np.argmin(np.median(dz, axis=0)))
            if np.mean(dz[:, label] > off) > 0.5 and best != label and np.median(dz[:, best]) < 0.5 * off:
                label = best
        out.append((poly, label))
    return out


def partition_rms(regions, planes, points: np.ndarray, outlier: float) -> float:
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


def open_pinches(regions, radius: float, tol: float):
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
                drop_close(np.asarray(r.coords)[:-1, :2], tol) for r in (poly.exterior, *poly.interiors)
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
                found = next(((i, v) for v in necks(rings, tol) if (round(v[0], 6), round(v[1], 6)) not in failed), None)
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


def necks(rings: list[np.ndarray], tol: float) -> np.ndarray:
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


def open_crossings(regions, radius: float, tol: float):
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


def drop_close(ring: np.ndarray, tol: float) -> np.ndarray:
    """Ring coordinates without runs of consecutive points closer than ``tol``."""
    keep = [0]
    for k in range(1, len(ring)):
        if np.hypot(*(ring[k] - ring[keep[-1]])) > tol:
            keep.append(k)
    if len(keep) > 1 and np.hypot(*(ring[keep[-1]] - ring[0])) <= tol:
        keep.pop()
    return ring[keep]


def arrangement(regions, planes, fp, grid: RoofGrid, u) -> list[tuple[shapely.Polygon, int]]:
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
