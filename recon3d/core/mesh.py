"""Polygon solids to welded triangle meshes without T-junctions.

Every product that needs triangles takes them from :func:`solid_mesh` (through
:meth:`recon3d.core.city.Solid.to_trimesh`): the OBJ and GLB exports, the model DSM,
volumes and the mesh checks. Mesh tools (trimesh, manifold3d, Blender) see a closed
shell only when

- triangles share vertices (one vertex per position, not per triangle corner);
- no vertex lies inside another triangle's edge (a T-junction): a polygon edge
  that a neighbour splits at one of its vertices is split there too, before the
  polygon is triangulated;
- every ring vertex is used: earcut drops collinear ring vertices when it joins a
  hole to the outer ring, which leaves a T-junction even in an edge-matched solid,
  so triangles whose edge runs over a ring vertex are split there;
- a polygon's triangles all keep the orientation of its outer ring (one decision
  per polygon, so sliver triangles cannot be flipped alone).

The polygons' own geometry is kept: vertices closer than ``tol`` are merged (the
first one's position is kept), T-junction vertices are only inserted in rings,
never moved, so the mesh encloses the volume of the polygons.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import NamedTuple

import mapbox_earcut
import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = [
    "WELD_TOLERANCE",
    "RingTable",
    "SolidMesh",
    "newell_normal",
    "points_on_segments",
    "snap_vertices",
    "solid_mesh",
    "split_ring_edges",
    "triangulate_surface",
    "triangulate_surfaces",
    "welded_rings",
]

#: Vertices closer than this (CRS units) are one vertex, and a vertex closer than
#: this to a polygon edge splits it: val3dity's snap tolerance, and the 1 mm that
#: CityJSON's quantisation keeps.
WELD_TOLERANCE = 1e-3

#: Up to this many (segment, point) pairs, :func:`points_on_segments` measures every pair.
_ALL_PAIRS = 1 << 14


class SolidMesh(NamedTuple):
    """Triangles of a solid, on welded vertices.

    Attributes
    ----------
    vertices : (n, 3) float64
        The distinct vertices the triangles use, in the order of their first index in
        the solid.
    faces : (m, 3) int64
        Triangles, counter-clockwise seen from outside, grouped by surface in the
        order of the solid's surfaces.
    surface : (m,) int64
        Index of each triangle's surface in ``Solid.surfaces``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    surface: np.ndarray


@dataclass(frozen=True)
class RingTable:
    """The rings of a solid's surfaces as one flat array (all rings' work at once: the
    mesh checks, the welding and the triangulation).

    Attributes
    ----------
    index : (m,) int64
        Vertex indices of every ring, ring after ring.
    sizes : (r,) int64
        Vertices per ring.
    owner : (r,) int64
        Surface of each ring.
    position : (r,) int64
        Place of each ring in its surface (0: the outer ring).
    """

    index: np.ndarray
    sizes: np.ndarray
    owner: np.ndarray
    position: np.ndarray

    @classmethod
    def of(cls, surfaces: list[list[np.ndarray]]) -> RingTable:
        rings = [np.asarray(r, np.int64).reshape(-1) for s in surfaces for r in s]
        counts = [len(s) for s in surfaces]
        return cls(
            np.concatenate(rings) if rings else np.zeros(0, np.int64),
            np.array([len(r) for r in rings], np.int64),
            np.repeat(np.arange(len(surfaces), dtype=np.int64), counts),
            np.concatenate([np.arange(c, dtype=np.int64) for c in counts]) if rings else np.zeros(0, np.int64),
        )

    @property
    def starts(self) -> np.ndarray:
        """(r,) where each ring begins in ``index``."""
        return np.r_[0, np.cumsum(self.sizes)[:-1]].astype(np.int64)

    @property
    def ring(self) -> np.ndarray:
        """(m,) the ring of each entry of ``index``."""
        return np.repeat(np.arange(len(self.sizes)), self.sizes)

    def following(self) -> np.ndarray:
        """(m,) position in ``index`` of the next vertex of the same ring (cyclic)."""
        nxt = np.arange(1, len(self.index) + 1)
        ends = self.starts + self.sizes - 1
        nonempty = self.sizes > 0
        nxt[ends[nonempty]] = self.starts[nonempty]
        return nxt

    def preceding(self) -> np.ndarray:
        """(m,) position in ``index`` of the vertex before each one in its ring (cyclic)."""
        before = np.empty(len(self.index), np.int64)
        before[self.following()] = np.arange(len(self.index))
        return before

    def newell_normals(self, vertices: np.ndarray) -> np.ndarray:
        """(r, 3) :func:`newell_normal` of every ring (sums in ring order)."""
        p = vertices[self.index]
        q = vertices[self.index[self.following()]]
        terms = (p - q)[:, [1, 2, 0]] * (p + q)[:, [2, 0, 1]]
        ring, r = self.ring, len(self.sizes)
        return np.column_stack([np.bincount(ring, terms[:, k], minlength=r) for k in range(3)])

    def subset(self, keep: np.ndarray) -> RingTable:
        """The table with only the vertices where ``keep`` (m,) and the rings left non-empty."""
        sizes = np.bincount(self.ring[keep], minlength=len(self.sizes))
        alive = sizes > 0
        return RingTable(self.index[keep], sizes[alive], self.owner[alive], self.position[alive])


def newell_normal(points: np.ndarray) -> np.ndarray:
    """Unnormalised normal of a (k, 3) polygon ring by Newell's method (robust to collinear runs).

    Its length is twice the ring's area.
    """
    p = np.asarray(points, dtype=np.float64)
    q = np.concatenate([p[1:], p[:1]])
    return np.einsum("ij,ij->j", (p - q)[:, [1, 2, 0]], (p + q)[:, [2, 0, 1]])


def snap_vertices(vertices: np.ndarray, snap: float) -> np.ndarray:
    """Canonical vertex id per vertex, merging vertices closer than ``snap``.

    Parameters
    ----------
    vertices : (n, 3) float
    snap : float

    Returns
    -------
    (n,) int64
        Equal ids for vertices in one cluster (single linkage within ``snap``);
        clusters are numbered in the order of their first vertex.
    """
    n = len(vertices)
    if n == 0:
        return np.zeros(0, np.int64)
    pairs = cKDTree(vertices).query_pairs(snap, output_type="ndarray")
    graph = scipy.sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64)


def points_on_segments(
    points: np.ndarray, start: np.ndarray, end: np.ndarray, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points lying inside segments (T-junctions).

    Parameters
    ----------
    points : (k, d) float
        Candidate points, d = 2 or 3.
    start, end : (e, d) float
        Segment ends.
    tol : float
        Largest distance of a point to the segment; a point within ``tol`` of either
        end is at that end, not inside.

    Returns
    -------
    segment : (h,) int64
        Segment of each hit, ascending.
    point : (h,) int64
        Point of each hit.
    t : (h,) float64
        Position of the point along its segment, in (0, 1); hits of one segment are
        sorted by it.
    """
    points, start, end = (np.asarray(a, dtype=np.float64) for a in (points, start, end))
    if not len(points) or not len(start):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    seg, pt = _near_pairs(points, start, end, tol)
    d = end[seg] - start[seg]
    rel = points[pt] - start[seg]
    length2 = np.einsum("ij,ij->i", d, d)
    t = np.einsum("ij,ij->i", rel, d) / np.maximum(length2, 1e-300)
    off = rel - t[:, None] * d
    length = np.sqrt(length2)
    hit = (np.einsum("ij,ij->i", off, off) <= tol * tol) & (t * length > tol) & ((1.0 - t) * length > tol)
    order = np.lexsort((t[hit], seg[hit]))
    return seg[hit][order], pt[hit][order], t[hit][order]


def _near_pairs(points: np.ndarray, start: np.ndarray, end: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(segment, point) pairs, (h,) int64 each: the points in each segment's ball grown by ``tol``."""
    if len(points) * len(start) <= _ALL_PAIRS:
        seg, pt = np.indices((len(start), len(points))).reshape(2, -1)
        return seg, pt
    tree = cKDTree(points)
    centre, radius = (start + end) / 2, np.linalg.norm(end - start, axis=1) / 2 + tol
    count = tree.query_ball_point(centre, radius, return_length=True)
    found = tree.query_ball_point(centre, radius, return_sorted=True)
    pt = np.fromiter(itertools.chain.from_iterable(found), np.int64, int(count.sum()))
    return np.repeat(np.arange(len(start)), count), pt


def split_ring_edges(vertices: np.ndarray, rings: list[np.ndarray], tol: float) -> list[np.ndarray]:
    """Rings with every vertex that lies inside one of their edges inserted there.

    Parameters
    ----------
    vertices : (n, 3) float
        Welded vertices: every one of them that lies within ``tol`` of the inside of
        a ring edge splits it.
    rings : list of (k,) int arrays
        Rings of vertex indices, not closed.
    tol : float

    Returns
    -------
    list of (k',) int64 arrays
        The same rings, k' >= k, the inserted vertices in order along each edge.
    """
    if not rings:
        return []
    flat = np.concatenate(rings).astype(np.int64)
    sizes = np.array([len(r) for r in rings])
    ends = np.cumsum(sizes)
    nxt = np.arange(1, len(flat) + 1)
    nxt[ends - 1] = ends - sizes  # a ring's last edge closes on its first vertex
    segment, point, t = points_on_segments(vertices, vertices[flat], vertices[flat[nxt]], tol)
    if not len(segment):
        return [np.asarray(r, np.int64) for r in rings]
    # each edge's start vertex (t = -1), then the vertices inside it, in order
    edge = np.r_[np.arange(len(flat)), segment]
    order = np.lexsort((np.r_[np.full(len(flat), -1.0), t], edge))
    merged = np.r_[flat, point][order]
    added = np.bincount(np.searchsorted(ends, segment, side="right"), minlength=len(rings))
    return np.split(merged, np.cumsum(sizes + added)[:-1])


def triangulate_surface(vertices: np.ndarray, rings: list[np.ndarray]) -> np.ndarray:
    """Triangles (m, 3) of vertex indices covering one planar surface with holes.

    The surface is triangulated by earcut in the plane of its largest projection
    (earcut is named explicitly so every machine produces the same triangles). All
    triangles take the orientation of the outer ring. Collinear ring vertices are
    where earcut goes wrong: it drops some (when it joins a hole to the outer ring)
    and folds flat triangles over others; the flat triangles are removed and every
    ring vertex inside a triangle edge splits it, so the triangles' boundary is made
    of the rings' own edges.

    Parameters
    ----------
    vertices : (n, 3) float
    rings : list of (k,) int arrays
        Outer ring, then holes.

    Returns
    -------
    (m, 3) int64
        Indices into ``vertices``; empty for a ring without area.
    """
    return triangulate_surfaces(vertices, [rings])[0]


def triangulate_surfaces(vertices: np.ndarray, surfaces: list[list[np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`triangulate_surface` of many surfaces at once.

    Only the earcut call runs per surface; the projection, the orientation and the
    checks for folds and dropped vertices run on all surfaces together (a solid has
    hundreds of small walls, and per-surface numpy calls cost more than earcut).

    Parameters
    ----------
    vertices : (n, 3) float
    surfaces : list of list of (k,) int arrays
        Outer ring then holes per surface; a surface without rings has no triangles.

    Returns
    -------
    faces : (m, 3) int64
        Indices into ``vertices``, grouped by surface in the order of ``surfaces``.
    surface : (m,) int64
        Index of each triangle's surface.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    live = np.array([s for s, rings in enumerate(surfaces) if rings], np.int64)
    if not len(live):
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    table = RingTable.of([surfaces[s] for s in live])
    index, sizes = table.index, table.sizes
    row_surface = table.owner[table.ring]  # live position of each ring row
    outer_ring = np.flatnonzero(table.position == 0)
    ring_count = np.diff(np.r_[outer_ring, len(sizes)])
    row_bounds = np.r_[table.starts[outer_ring], len(index)]
    normal = table.newell_normals(vertices)[outer_ring]
    # the plane of the largest projection; of two equal ones (a wall at 45 degrees) the
    # first, whatever the rounding of the sums (which differs between numpy's kernels)
    size = np.abs(normal)
    drop = np.argmax(size >= (1.0 - 1e-9) * size.max(axis=1, keepdims=True), axis=1)
    xy = np.take_along_axis(vertices[index], np.array([[1, 2], [0, 2], [0, 1]])[drop][row_surface], axis=1)
    ends = (np.cumsum(sizes) - np.repeat(row_bounds[:-1], ring_count)).astype(np.uint32)
    ring_bounds = np.r_[outer_ring, len(sizes)]
    pieces, counts = [], np.zeros(len(live), np.int64)
    for k in np.flatnonzero(normal.any(axis=1)):
        a, b = row_bounds[k], row_bounds[k + 1]
        tri = mapbox_earcut.triangulate_float64(xy[a:b], ends[ring_bounds[k] : ring_bounds[k + 1]])
        pieces.append(tri.astype(np.int64) + a)
        counts[k] = len(tri) // 3
    tri = np.concatenate(pieces).reshape(-1, 3) if pieces else np.zeros((0, 3), np.int64)
    tri_surface = np.repeat(np.arange(len(live)), counts)
    # twice the outer ring's area in (x, y), (y, z) or (x, z)
    outer = normal[np.arange(len(live)), drop] * np.where(drop == 1, -1.0, 1.0)
    area = np.bincount(tri_surface, weights=_area2(xy[tri]), minlength=len(live))
    flip = (np.sign(area) != np.sign(outer))[tri_surface]
    tri[flip] = tri[flip][:, ::-1]
    extent = np.maximum.reduceat(xy, row_bounds[:-1], axis=0) - np.minimum.reduceat(xy, row_bounds[:-1], axis=0)
    tol = 1e-9 * np.maximum(extent.max(axis=1), 1.0)
    used = np.zeros(len(index), bool)
    used[tri] = True
    folded = np.bincount(tri_surface[_flat(xy[tri], tol[tri_surface])], minlength=len(live)) > 0
    dropped = np.bincount(row_surface[~used], minlength=len(live)) > 0
    faces = index[tri]
    repair = np.flatnonzero((folded | dropped) & (counts > 0))
    if len(repair):
        # nothing lies inside an edge elsewhere: every ring vertex used, no fold
        parts = np.split(faces, np.cumsum(counts)[:-1])
        for k in repair:
            a, b = row_bounds[k], row_bounds[k + 1]
            parts[k] = _unfolded(index[a:b], xy[a:b], tri[tri_surface == k] - a, tol[k])
            counts[k] = len(parts[k])
        faces = np.concatenate(parts)
    return faces, np.repeat(live, counts)


def _unfolded(index: np.ndarray, xy: np.ndarray, tri: np.ndarray, tol: float) -> np.ndarray:
    """One surface's earcut triangles without flat folds, split at the ring vertices
    inside their edges.

    Parameters
    ----------
    index : (k,) int64
        The surface's ring vertices (vertex ids), rings one after the other.
    xy : (k, 2) float
        Their projection.
    tri : (m, 3) int64
        earcut's triangles, indices into ``index``, oriented.
    """
    unique, first, inverse = np.unique(index, return_index=True, return_inverse=True)
    tri, xy = inverse[tri], xy[first]  # a vertex twice in the rings (rings touching) is one point
    return unique[_split_on_edges(xy, tri[~_flat(xy[tri], tol)], tol)]


def _flat(triangles: np.ndarray, tol) -> np.ndarray:
    """(m,) True for (m, 3, 2) triangles whose height is at most ``tol`` (a float, or
    (m,) one per triangle): a corner on the opposite edge.

    earcut leaves such triangles over collinear ring vertices; dropping them and
    splitting the neighbour's edge at the vertex gives the same cover, without a fold.
    """
    side = triangles[:, [1, 2, 0]] - triangles
    longest = np.sqrt(np.einsum("tij,tij->ti", side, side).max(axis=1))
    return np.abs(_area2(triangles)) <= tol * longest


def _area2(triangles: np.ndarray) -> np.ndarray:
    """(m,) twice the signed areas (counter-clockwise positive) of (m, 3, 2) triangles."""
    u, v = triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]


def _split_on_edges(points: np.ndarray, tri: np.ndarray, tol: float) -> np.ndarray:
    """Triangles split wherever one of ``points`` lies inside one of their edges.

    A triangle (u, v, w) with points p1..pc inside its edge u -> v becomes the fan
    (u, p1, w), (p1, p2, w), ..., (pc, v, w), in the same orientation; a triangle
    with points on several edges is split edge by edge over the rounds.

    Parameters
    ----------
    points : (k, d) float
    tri : (m, 3) int64
        Indices into ``points``.
    tol : float

    Returns
    -------
    (m', 3) int64
        Each triangle's pieces where it stood.
    """
    for _ in range(len(points)):  # each round uses up at least one (point, edge) pair
        # (3 m, 3): row 3 i + k is edge k of triangle i as (u, v, apex)
        edges = np.stack([tri, tri[:, [1, 2, 0]], tri[:, [2, 0, 1]]], axis=2).reshape(-1, 3)
        segment, point, _ = points_on_segments(points, points[edges[:, 0]], points[edges[:, 1]], tol)
        if not len(segment):
            return tri
        owner = segment // 3
        first = np.r_[True, owner[1:] != owner[:-1]]
        chosen = segment[first][np.cumsum(first) - 1]  # each triangle's first edge with points
        keep = segment == chosen
        tri = _fan(tri, edges, segment[keep], point[keep])
    return tri


def _fan(tri: np.ndarray, edges: np.ndarray, segment: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Replace each triangle owning a ``segment`` by its fan over the points of that edge.

    ``segment`` (h,) is sorted, one edge per triangle, its points in order along it.
    """
    edge, count = np.unique(segment, return_counts=True)
    u, v, apex = edges[edge].T
    start = np.r_[0, np.cumsum(count + 2)[:-1]]
    chain = np.empty(int((count + 2).sum()), np.int64)  # u, p1..pc, v per split triangle
    chain[start] = u
    chain[start + count + 1] = v
    rank = np.arange(len(segment)) - np.repeat(np.r_[0, np.cumsum(count)[:-1]], count)
    chain[np.repeat(start, count) + 1 + rank] = point
    last = np.zeros(len(chain), bool)
    last[start + count + 1] = True
    pieces = np.column_stack([chain[:-1], chain[1:], np.repeat(apex, count + 2)[:-1]])[~last[:-1]]
    source = np.r_[np.setdiff1d(np.arange(len(tri)), edge // 3), np.repeat(edge // 3, count + 1)]
    faces = np.concatenate([np.delete(tri, edge // 3, axis=0), pieces])
    return faces[np.argsort(source, kind="stable")]


def solid_mesh(vertices: np.ndarray, surfaces: list[list[np.ndarray]], tol: float = WELD_TOLERANCE) -> SolidMesh:
    """Welded, T-junction-free triangles of a polygon solid.

    Parameters
    ----------
    vertices : (n, 3) float
    surfaces : list of list of (k,) int arrays
        Outer ring then holes per surface, outer rings counter-clockwise from outside.
    tol : float
        Vertices closer than this merge; a vertex closer than this to the inside of
        a ring edge splits it (CRS units).

    Returns
    -------
    SolidMesh
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    label = snap_vertices(vertices, tol)
    kept = welded_rings(label, surfaces)
    flat = [r for rings in kept for r in rings]
    used = np.unique(np.concatenate(flat)) if flat else np.zeros(0, np.int64)
    points = vertices[np.unique(label, return_index=True)[1][used]]
    compact = np.zeros(len(vertices), np.int64)
    compact[used] = np.arange(len(used))
    split = iter(split_ring_edges(points, [compact[r] for r in flat], tol))
    faces, surface = triangulate_surfaces(points, [[next(split) for _ in rings] for rings in kept])
    keep = ~_cancelling_pairs(faces)
    return SolidMesh(points, faces[keep], surface[keep])


def _cancelling_pairs(faces: np.ndarray) -> np.ndarray:
    """(m,) True for triangles that cancel: the same three vertices wound both ways.

    Where two surfaces meet along a polyline whose middle vertex is almost straight
    (off the line by more than the fold test's 1e-9 of the surface's extent, less
    than the weld tolerance), earcut may cut that vertex's sliver off both surfaces:
    one triangle, twice, facing opposite ways. The pair encloses nothing, but its long
    edge is then used by four triangles and the mesh is not watertight for trimesh,
    Blender or a glTF validator. Dropping both leaves the same closed surface. Of k
    and l copies wound each way, min(k, l) of each are dropped, the first ones.

    Parameters
    ----------
    faces : (m, 3) int
    """
    drop = np.zeros(len(faces), bool)
    if len(faces) < 2:
        return drop
    f = np.asarray(faces)
    odd = ((f[:, 0] > f[:, 1]).astype(np.int8) + (f[:, 0] > f[:, 2]) + (f[:, 1] > f[:, 2])) % 2 == 1
    _, group, count = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True, return_counts=True)
    group = group.ravel()
    for g in np.flatnonzero(count > 1):  # rare: a few slivers per solid at most
        members = np.flatnonzero(group == g)
        ways = members[odd[members]], members[~odd[members]]
        n = min(len(ways[0]), len(ways[1]))
        drop[ways[0][:n]] = drop[ways[1][:n]] = True
    return drop


def welded_rings(label: np.ndarray, surfaces: list[list[np.ndarray]]) -> list[list[np.ndarray]]:
    """Every surface's rings as (k,) vertex ids ``label[ring]``, repeats removed; no ring without an outer one.

    A vertex equal to the one before it (cyclically) is dropped; rings left with fewer
    than 3 vertices are dropped; a surface whose outer ring is dropped has none.
    """
    table = RingTable.of(surfaces)
    table = RingTable(label[table.index], table.sizes, table.owner, table.position)
    welded = table.subset(table.index != table.index[table.preceding()])
    whole = welded.sizes >= 3
    outer = np.zeros(len(surfaces), bool)
    outer[welded.owner[whole & (welded.position == 0)]] = True
    out: list[list[np.ndarray]] = [[] for _ in surfaces]
    rings = np.split(welded.index, np.cumsum(welded.sizes)[:-1]) if len(welded.sizes) else []
    for ring, s, keep in zip(rings, welded.owner.tolist(), whole.tolist(), strict=True):
        if keep and outer[s]:
            out[s].append(ring)
    return out
