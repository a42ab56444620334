"""Solids by extrusion: LoD1 prisms, and LoD1.3 / LoD2.2 solids assembled from a planar
partition (roof polygons at their planes' heights, step walls, outer walls, floor).

No boolean operation is involved: the surfaces are exact planar polygons with holes,
every shell edge shared by exactly two surfaces, outer rings counter-clockwise seen
from outside (CityJSON style).
"""

from __future__ import annotations

import math as _math

import numpy as np
import shapely

from recon3d.buildings.outline import remove_spikes
from recon3d.buildings.roofgrid import LodFailure, plane_height
from recon3d.core.city import Solid
from recon3d.core.geo import LocalFrame
from recon3d.core.mesh import RingTable

__all__ = ["MinRootSets", "clean_footprint", "lod1_solid", "partition_solid"]


def clean_footprint(polygon: shapely.Polygon, tolerance: float) -> shapely.Polygon | None:
    """Footprint ready for extrusion: valid, repeated and collinear vertices and
    zero-width spikes removed (a spike's edges would be shared by four faces),
    exterior counter-clockwise and holes clockwise. None when nothing with area is left.
    """
    poly = shapely.remove_repeated_points(polygon, tolerance)
    if poly.geom_type == "Polygon" and poly.is_valid:
        poly = remove_spikes(poly)
        if poly is None:
            return None
    poly = shapely.make_valid(poly)
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


def partition_solid(regions, planes, g: float, u) -> Solid:
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
        raise LodFailure("invalid_mesh", "no region left in the footprint")
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
        raise LodFailure("invalid_mesh", "no region left in the footprint")
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
        h = plane_height(plane_of[f], coords[ids, 0], coords[ids, 1])
        if np.any(h < g + min_wall - eps):
            raise LodFailure("poor_fit", "a roof plane reaches down to the ground")
        entries.append(np.column_stack([ids, np.full(len(ids), f), h]))
    directed = {}
    for f, rr in enumerate(rings):
        for r in rr:
            for a, b in _ring_edges(r):
                if (a, b) in directed:
                    raise LodFailure("invalid_mesh", "two parts overlap along an edge")
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
    n = len(walls)
    normals, offsets = _wall_planes(verts, walls)
    sets = MinRootSets(n)
    owner: dict[tuple[int, int], int] = {}
    for i, w in enumerate(walls):
        for a, b in _ring_edges(w):
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
        edges = {(a, b) for i in members for a, b in _ring_edges(walls[i])}
        rim = np.array(sorted(e for e in edges if (e[1], e[0]) not in edges), dtype=np.int64)
        normal = np.append(normals[members[0]], 0.0)
        try:
            out += _face_rings(verts, rim, normal)
        except LodFailure:
            out += [[walls[i]] for i in members]
    return out


def _wall_planes(verts: np.ndarray, walls: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Unit horizontal normals (n, 2) of the walls (their Newell normals' x and y; 0 for
    a wall without area) and their offsets (n,): the mean of ``xy . normal``."""
    table = RingTable.of([[w] for w in walls])
    nv = table.newell_normals(verts)[:, :2]
    norm = np.sqrt(np.einsum("ij,ij->i", nv, nv))
    unit = np.divide(nv, norm[:, None], out=np.zeros_like(nv), where=norm[:, None] > 0)
    along = np.einsum("ij,ij->i", verts[table.index, :2], unit[table.ring])
    return unit, np.bincount(table.ring, along, minlength=len(walls)) / np.maximum(table.sizes, 1)


def _ring_edges(ring: np.ndarray) -> list[tuple[int, int]]:
    """The directed edges (a, b) of a closed ring of vertex ids, the last one back to the first."""
    ids = ring.tolist()
    return list(zip(ids, ids[1:] + ids[:1], strict=True))


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


def _dedupe(ring: list[int]) -> list[int]:
    """Ring without consecutive repeats (cyclically)."""
    out = [v for i, v in enumerate(ring) if v != ring[i - 1]] if len(ring) > 1 else list(ring)
    return out


def _insert_on_edges(ring: np.ndarray, coords: np.ndarray, tol: float, new_from: int = 0) -> np.ndarray:
    """Ring with every vertex (index >= ``new_from``) lying within ``tol`` of one of its
    edges inserted into that edge, in order; consecutive repeats dropped."""
    cand = np.arange(new_from, len(coords))
    p = coords[ring]
    d = coords[np.roll(ring, -1)] - p
    length2 = np.einsum("ij,ij->i", d, d)
    c = coords[cand]
    # (edges, candidates): position along each edge and distance to it
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.matmul(c[None] - p[:, None], d[:, :, None])[:, :, 0] / length2[:, None]
        dist = np.linalg.norm(c[None] - (p[:, None] + t[..., None] * d[:, None]), axis=2)
    near = (t > 1e-9) & (t < 1 - 1e-9) & (length2 > 0)[:, None]
    edge, which = np.nonzero(near & (dist <= tol))
    order = np.lexsort((t[edge, which], edge))  # along each edge; equal positions in index order
    edge, found = edge[order], cand[which[order]]
    ids = ring.tolist()
    out = []
    inserted = np.split(found, np.searchsorted(edge, np.arange(1, len(ids))))
    for k, here in enumerate(inserted):
        out.append(ids[k])
        ends = (ids[k], ids[(k + 1) % len(ids)])
        out.extend(j for j in here.tolist() if j not in ends)
    return np.array(_dedupe(out), dtype=np.int64)


def _crossings(rings, coords, plane_of, eps) -> np.ndarray:
    """Points where two neighbouring parts' planes cross along their common edge."""
    owner = {}
    for f, rr in enumerate(rings):
        for r in rr:
            for a, b in _ring_edges(r):
                owner[(a, b)] = f
    out = []
    for (a, b), f in owner.items():
        g = owner.get((b, a))
        if g is None or g < f:
            continue
        pa, pb = coords[a], coords[b]
        da = plane_height(plane_of[f], *pa) - plane_height(plane_of[g], *pa)
        db = plane_height(plane_of[f], *pb) - plane_height(plane_of[g], *pb)
        if da * db < 0 and abs(da) > eps and abs(db) > eps:
            out.append(pa + da / (da - db) * (pb - pa))
    return np.array(out).reshape(-1, 2)


class MinRootSets:
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
        raise LodFailure("invalid_mesh", "a face has no outer ring")
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
