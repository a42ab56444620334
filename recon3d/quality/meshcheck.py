"""val3dity-style geometric validation of building solids.

The checks follow the error codes of val3dity and of the OGC CityGML Quality
Interoperability Experiment (https://github.com/tudelft3d/CityGML-QIE-3Dvalidation,
``errors/errors.md``), so a report can be compared with val3dity's:

====  ==================================  ============================================
code  name                                meaning
====  ==================================  ============================================
101   TOO_FEW_POINTS                      a ring has fewer than 3 (distinct) points
102   CONSECUTIVE_POINTS_SAME             two consecutive points within ``snap``
105   RING_COLLAPSED                      a ring has (almost) no area: a degenerate
                                          surface collapsed to a line or a point
203   NON_PLANAR_POLYGON_DISTANCE_PLANE   a point lies further than ``planarity_tol``
                                          from the surface's least-squares plane
301   TOO_FEW_POLYGONS                    fewer than 4 surfaces
302   NOT_CLOSED                          an edge is used by one ring only (a hole)
303   NON_MANIFOLD_VERTEX                 the surfaces around a vertex form more than
                                          one umbrella
304   NON_MANIFOLD_EDGE                   an edge is used by more than 2 rings
307   POLYGON_WRONG_ORIENTATION           an edge is traversed twice in the same
                                          direction (a surface is flipped)
405   WRONG_ORIENTATION_SHELL             the shell is inside out (signed volume <= 0)
====  ==================================  ============================================

Vertices closer than ``snap`` are merged first (as val3dity does), and the shell
topology is checked on the polygon rings, not on a triangulation, so a surface
split into triangles elsewhere would show up as 302. As in val3dity, 303 and 405 are
only tested on a shell that is closed, edge-manifold and consistently oriented.

The triangle meshes of the exports (GLB, OBJ) are checked as other tools load them
(:func:`check_mesh_file`): each building's mesh, read by trimesh without merging
anything, must be watertight, consistently wound, enclose a positive volume
(outward normals) and be accepted by manifold3d (status ``NoError``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components

from recon3d.core.city import CityModel, Solid
from recon3d.core.mesh import RingTable, snap_vertices

log = logging.getLogger(__name__)

__all__ = [
    "ISSUE_NAMES",
    "MeshCheck",
    "MeshIssue",
    "building_meshes",
    "check_city",
    "check_mesh",
    "check_mesh_file",
    "check_solid",
    "manifold_status",
    "snap_vertices",
    "triangle_issues",
]

#: Error code -> name, as in val3dity / the CityGML QIE.
ISSUE_NAMES: dict[int, str] = {
    101: "TOO_FEW_POINTS",
    102: "CONSECUTIVE_POINTS_SAME",
    105: "RING_COLLAPSED",
    203: "NON_PLANAR_POLYGON_DISTANCE_PLANE",
    301: "TOO_FEW_POLYGONS",
    302: "NOT_CLOSED",
    303: "NON_MANIFOLD_VERTEX",
    304: "NON_MANIFOLD_EDGE",
    307: "POLYGON_WRONG_ORIENTATION",
    405: "WRONG_ORIENTATION_SHELL",
}


@dataclass(frozen=True)
class MeshIssue:
    """One validation error of a solid.

    Attributes
    ----------
    code : int
        val3dity error code (see :data:`ISSUE_NAMES`).
    name : str
        val3dity error name.
    detail : str
        Human-readable specifics (distances, counts, vertex or surface numbers).
    surface : int or None
        Index of the offending surface in ``Solid.surfaces``; None for shell errors.
    """

    code: int
    name: str
    detail: str
    surface: int | None = None


def _issue(code: int, detail: str, surface: int | None = None) -> MeshIssue:
    return MeshIssue(code, ISSUE_NAMES[code], detail, surface)


def check_solid(
    solid: Solid, *, planarity_tol: float = 0.01, snap: float = 0.001
) -> list[MeshIssue]:
    """Validate one solid (a single outer shell).

    Parameters
    ----------
    solid : Solid
        Surfaces as rings of vertex indices, outer rings counter-clockwise from outside.
    planarity_tol : float
        Largest allowed distance of a vertex to its surface's fitted plane (203), in
        the solid's length units (val3dity's default: 1 cm).
    snap : float
        Vertices closer than this are the same vertex (val3dity's default: 1 mm).

    Returns
    -------
    list of MeshIssue
        Empty for a valid solid.
    """
    vertices = np.asarray(solid.vertices, dtype=np.float64)
    vid = snap_vertices(vertices, snap)
    issues: list[MeshIssue] = []
    if len(solid.surfaces) < 4:
        issues.append(_issue(301, f"{len(solid.surfaces)} surfaces, a solid needs at least 4"))
    table = RingTable.of(solid.surfaces)
    found, clean = _ring_issues(vertices, vid, table, snap, planarity_tol)
    issues += found
    ids, following = vid[clean.index], clean.following()
    shell = _shell_issues(np.column_stack([ids, ids[following]]), clean.owner[clean.ring])
    issues += shell
    if not shell and len(ids):
        issues += _vertex_manifold(ids, following)
        issues += _orientation(solid)
    return issues


def _ring_issues(
    vertices: np.ndarray, vid: np.ndarray, table: RingTable, snap: float, tol: float
) -> tuple[list[MeshIssue], RingTable]:
    """Ring-level checks (101, 102, 105) and planarity (203) of every surface.

    Returns
    -------
    issues : list of MeshIssue
        By surface, each surface's ring issues in ring order, then its 203.
    clean : RingTable
        The usable rings (3 distinct points or more), consecutive repeats removed.
    """
    ring = table.ring
    ids = vid[table.index]
    repeat = ids == ids[table.following()]
    short = table.sizes < 3
    repeat &= ~short[ring]
    repeats = np.bincount(ring[repeat], minlength=len(table.sizes))
    distinct = table.sizes - repeats
    usable = ~short & (distinct >= 3)
    clean = table.subset(~repeat & usable[ring])
    collapsed = _collapsed(vertices, clean, snap)
    keyed = []  # (surface, ring position, order, issue): the order of a surface-by-surface check
    for r in np.flatnonzero(short | (repeats > 0) | ~usable):
        s, j = int(table.owner[r]), int(table.position[r])
        where = _ring_name(j)
        if short[r]:
            keyed.append((s, j, 0, _issue(101, f"{where} has {table.sizes[r]} points", s)))
            continue
        if repeats[r]:
            keyed.append((s, j, 0, _issue(102, f"{where}: {int(repeats[r])} repeated points", s)))
        if distinct[r] < 3:
            keyed.append((s, j, 1, _issue(101, f"{where} has {int(distinct[r])} distinct points", s)))
    for r in np.flatnonzero(collapsed):
        s, j = int(clean.owner[r]), int(clean.position[r])
        keyed.append((s, j, 2, _issue(105, f"{_ring_name(j)} has no area (degenerate surface)", s)))
    for s, worst in _planarity(vertices, clean, tol):
        keyed.append((s, np.inf, 0, _issue(203, f"a vertex is {worst:.4f} from the fitted plane (tolerance {tol})", s)))
    keyed.sort(key=lambda k: k[:3])
    return [k[3] for k in keyed], clean


def _ring_name(position: int) -> str:
    return f"ring {position}" if position else "outer ring"


def _collapsed(vertices: np.ndarray, table: RingTable, snap: float) -> np.ndarray:
    """(r,) True for rings thinner than ``snap``: area < snap * perimeter / 2.

    A w x L rectangle passes this test exactly when w < snap. The area is half the
    length of the ring's Newell normal.
    """
    p = vertices[table.index]
    q = vertices[table.index[table.following()]]
    normal = table.newell_normals(vertices)
    perimeter = np.bincount(table.ring, np.linalg.norm(q - p, axis=1), minlength=len(table.sizes))
    return 0.5 * np.linalg.norm(normal, axis=1) < 0.5 * snap * perimeter


def _planarity(vertices: np.ndarray, table: RingTable, tol: float) -> list[tuple[int, float]]:
    """(surface, largest distance) where a vertex of a surface's rings is further than
    ``tol`` from their least-squares plane (the direction of least spread)."""
    if not len(table.index):
        return []
    surface = table.owner[table.ring]  # rings come surface by surface: groups are contiguous
    first = np.r_[True, surface[1:] != surface[:-1]]
    starts, group = np.flatnonzero(first), np.cumsum(first) - 1
    points = vertices[table.index]
    mean = np.add.reduceat(points, starts, axis=0) / np.diff(np.r_[starts, len(points)])[:, None]
    centred = points - mean[group]
    scatter = np.add.reduceat(centred[:, :, None] * centred[:, None, :], starts, axis=0)
    normal = np.linalg.eigh(scatter)[1][:, :, 0]
    distance = np.abs(np.einsum("ij,ij->i", centred, normal[group]))
    worst = np.maximum.reduceat(distance, starts)
    return [(int(surface[starts[g]]), float(worst[g])) for g in np.flatnonzero(worst > tol)]


def check_city(
    city: CityModel, *, planarity_tol: float = 0.01, snap: float = 0.001
) -> dict[str, dict[str, list[MeshIssue]]]:
    """Validate every solid of a city model.

    Returns
    -------
    dict
        ``{building id: {lod: [MeshIssue, ...]}}`` for every building with a solid;
        an empty list means the solid is valid. ``snap`` and ``planarity_tol`` are
        in CRS units.
    """
    report: dict[str, dict[str, list[MeshIssue]]] = {}
    for building in city.buildings:
        if not building.solids:
            continue
        report[building.id] = {
            lod: check_solid(solid, planarity_tol=planarity_tol, snap=snap)
            for lod, solid in sorted(building.solids.items(), key=lambda kv: float(kv[0]))
            if solid.kind == "Solid"  # surfaces read from another tool's MultiSurface are no solid to check
        }
    n_bad = sum(bool(v) for lods in report.values() for v in lods.values())
    log.info("mesh check: %d of %d solids have issues", n_bad, sum(map(len, report.values())))
    return report


def _pair_keys(pairs: np.ndarray) -> np.ndarray:
    """(m,) int64 keys of (m, 2) non-negative int pairs, in the pairs' lexicographic order
    (``np.unique`` on keys instead of rows: the same groups, several times faster)."""
    pairs = np.asarray(pairs, np.int64)
    base = int(pairs[:, 1].max()) + 1 if len(pairs) else 1
    return pairs[:, 0] * base + pairs[:, 1]


def _shell_issues(edges: np.ndarray, owner: np.ndarray) -> list[MeshIssue]:
    """302, 304 and 307 from how often, and in which direction, each ring edge is used.

    ``edges`` (m, 2) are the directed edges of every ring (snapped vertex ids),
    ``owner`` (m,) the surface of each.
    """
    if not len(edges):
        return [_issue(302, "no usable surface")]
    _, inverse, count = np.unique(_pair_keys(np.sort(edges, axis=1)), return_inverse=True, return_counts=True)
    uses = count[inverse.reshape(-1)]
    issues = []
    if (count == 1).any():
        where = _few(np.unique(owner[uses == 1]))
        n = int((count == 1).sum())
        issues.append(_issue(302, f"{n} edges used by one surface only (surfaces {where})"))
    if (count > 2).any():
        where = _few(np.unique(owner[uses > 2]))
        n = int((count > 2).sum())
        issues.append(_issue(304, f"{n} edges used by more than 2 surfaces (surfaces {where})"))
    return issues + _flipped(edges, owner, uses)


def _flipped(edges: np.ndarray, owner: np.ndarray, uses: np.ndarray) -> list[MeshIssue]:
    """307 for the surfaces most of whose shared edges run the same way as their neighbour's.

    An edge shared by two correctly oriented surfaces is traversed once in each
    direction. A flipped surface conflicts on all its edges, its neighbours on one
    each, so surfaces conflicting on more than half of their shared edges are named.
    """
    _, inverse, count = np.unique(_pair_keys(edges), return_inverse=True, return_counts=True)
    same = (count[inverse.reshape(-1)] > 1) & (uses == 2)
    if not same.any():
        return []
    n = int(owner.max()) + 1
    shared = np.bincount(owner[uses == 2], minlength=n)
    bad = np.bincount(owner[same], minlength=n)
    flipped = np.flatnonzero(bad * 2 > np.maximum(shared, 1))
    detail = "{} of {} shared edges run the same way as the neighbour's"
    if not len(flipped):
        return [_issue(307, f"{int(same.sum()) // 2} edges traversed twice in the same direction")]
    return [_issue(307, detail.format(bad[s], shared[s]), int(s)) for s in flipped]


def _vertex_manifold(centre: np.ndarray, following: np.ndarray) -> list[MeshIssue]:
    """303 where the surfaces around a vertex form several umbrellas (pinched vertices).

    ``centre`` (m,) are the snapped vertex ids of every ring, ring after ring, and
    ``following`` (m,) the position of each one's next vertex in its ring. The link
    of vertex v joins, for every ring corner (prev, v, next), the nodes (v, prev) and
    (v, next); v is manifold when its link is one connected cycle.
    """
    preceding = np.empty_like(following)
    preceding[following] = np.arange(len(following))
    prev, nxt = centre[preceding], centre[following]
    pairs = np.column_stack([np.r_[centre, centre], np.r_[prev, nxt]])
    _, first, inverse = np.unique(_pair_keys(pairs), return_index=True, return_inverse=True)
    nodes, inverse = pairs[first], inverse.reshape(-1)
    m = len(centre)
    shape = (len(nodes), len(nodes))
    graph = scipy.sparse.coo_matrix((np.ones(m), (inverse[:m], inverse[m:])), shape=shape)
    _, label = connected_components(graph, directed=False)
    umbrellas = np.unique(_pair_keys(np.column_stack([nodes[:, 0], label])))
    vertex, fans = np.unique(umbrellas // (int(label.max()) + 1), return_counts=True)
    pinched = vertex[fans > 1]
    if not len(pinched):
        return []
    return [_issue(303, f"{len(pinched)} vertices where separate parts of the shell touch")]


def _orientation(solid: Solid) -> list[MeshIssue]:
    """405 when the triangulated shell has a signed volume <= 0 (normals point inward)."""
    vertices, faces, _ = solid.mesh()
    if not len(faces):
        return []
    v = vertices - vertices.mean(axis=0)
    a, b, c = (v[faces[:, k]] for k in range(3))
    volume = float(np.einsum("ij,ij->", a, np.cross(b, c))) / 6.0
    if volume > 0:
        return []
    return [_issue(405, f"signed volume {volume:.4g} <= 0: the shell is inside out")]


def _few(values: np.ndarray, limit: int = 6) -> str:
    """Comma-separated first ``limit`` values, with an ellipsis when there are more."""
    text = ", ".join(str(int(v)) for v in values[:limit])
    return text + (", ..." if len(values) > limit else "")


# --------------------------------------------------------------------------- meshes of the exports


def triangle_issues(solid: Solid) -> list[MeshIssue]:
    """302, 304 and 307 of the triangles the exports hold (:meth:`Solid.mesh`).

    Every edge must be used by exactly two triangles, once each way: what trimesh,
    Blender and glTF validators ask of a closed mesh. A valid polygon shell can still
    be triangulated into a mesh that is not (see :func:`check_solid`, which looks at
    the rings only); this check sees the triangulation's faults.
    """
    _, faces, surface = solid.mesh()
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return [replace(i, detail=f"in the triangles: {i.detail}") for i in _shell_issues(edges, np.tile(surface, 3))]


@dataclass(frozen=True)
class MeshCheck:
    """trimesh's and manifold3d's verdict on the mesh of one building in a GLB or OBJ file.

    Attributes
    ----------
    id : str
        Building id (GLB node extras) or OBJ object name.
    kind : str
        "Solid", or "MultiSurface" for surfaces that close no volume (not checked).
    triangles : int
    watertight : bool
        trimesh: every edge shared by exactly two triangles.
    winding : bool
        trimesh: every shared edge traversed once in each direction.
    volume : float
        Signed volume (positive: normals point outward).
    manifold : str
        Status of ``manifold3d.Manifold`` built from the vertices and triangles.
    """

    id: str
    kind: str
    triangles: int
    watertight: bool
    winding: bool
    volume: float
    manifold: str

    @property
    def ok(self) -> bool:
        """True for a closed, outward, manifold shell; MultiSurface meshes always pass."""
        return self.kind != "Solid" or not self.problems()

    def problems(self) -> list[str]:
        """What is wrong with a solid's mesh, in words (empty when it passes)."""
        found = [] if self.watertight else ["not watertight"]
        found += [] if self.winding else ["winding not consistent"]
        found += [] if self.volume > 0 else [f"volume {self.volume:.4g} <= 0 (inside out)"]
        found += [] if self.manifold == "NoError" else [f"manifold3d {self.manifold}"]
        return found


def manifold_status(vertices: np.ndarray, faces: np.ndarray) -> str:
    """Name of manifold3d's status for a mesh: "NoError" when it is a manifold solid.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
    """
    import manifold3d

    mesh = manifold3d.Mesh(
        vert_properties=np.ascontiguousarray(vertices, dtype=np.float32),
        tri_verts=np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1, 3),
    )
    return manifold3d.Manifold(mesh).status().name


def check_mesh(mesh, building_id: str, kind: str = "Solid") -> MeshCheck:
    """Check one building's :class:`trimesh.Trimesh` as loaded, vertices not merged."""
    faces = np.asarray(mesh.faces)
    return MeshCheck(
        id=str(building_id),
        kind=kind,
        triangles=len(faces),
        watertight=bool(mesh.is_watertight),
        winding=bool(mesh.is_winding_consistent),
        volume=float(mesh.volume) if len(faces) else 0.0,
        manifold=manifold_status(mesh.vertices, faces) if len(faces) else "Empty",
    )


def building_meshes(path) -> list[tuple[str, str, object]]:
    """The building meshes of a GLB or OBJ export, loaded by trimesh as they are stored.

    A GLB gives one mesh per node (``extras["id"]``, ``extras["geometry_type"]``); an
    OBJ one mesh per object (``trimesh.load(path, split_objects=True,
    group_material=False, process=False)``), MultiSurface objects marked by
    :data:`recon3d.io.obj.SURFACES_COMMENT`.

    Returns
    -------
    list of (id, kind, trimesh.Trimesh)
        In file order.
    """
    import trimesh

    from recon3d.errors import InputError
    from recon3d.io import require_file

    path = require_file(path, "mesh")
    suffix = path.suffix.lower()
    try:
        if suffix in (".glb", ".gltf"):
            return _glb_meshes(trimesh.load(path, force="scene"))
        if suffix == ".obj":
            scene = trimesh.load(path, force="scene", split_objects=True, group_material=False, process=False)
            return _obj_meshes(scene, path.read_text(encoding="utf-8", errors="replace"))
    except (ValueError, KeyError, IndexError, OSError) as exc:
        raise InputError(f"{path}: cannot read the meshes ({exc})") from exc
    raise InputError(f"{path}: not a GLB or OBJ file")


def _glb_meshes(scene) -> list[tuple[str, str, object]]:
    """(id, kind, mesh) per geometry of a loaded GLB scene, in its node's frame."""
    out = []
    for name, mesh in scene.geometry.items():
        nodes = scene.graph.geometry_nodes.get(name, [])
        if nodes:
            transform, _ = scene.graph[nodes[0]]
            if not np.allclose(transform, np.eye(4)):
                mesh = mesh.copy()
                mesh.apply_transform(transform)
        meta = mesh.metadata
        out.append((str(meta.get("id", name)), str(meta.get("geometry_type", "Solid")), mesh))
    return out


def _obj_meshes(scene, text: str) -> list[tuple[str, str, object]]:
    """(id, kind, mesh) per object of a loaded OBJ, in file order."""
    from recon3d.io.obj import SURFACES_COMMENT

    order, surfaces, current = [], set(), None
    for line in text.splitlines():
        if line.startswith("o "):
            current = line[2:].strip()
            order.append(current)
        elif line.strip() == SURFACES_COMMENT and current is not None:
            surfaces.add(current)
    rank = {name: i for i, name in enumerate(order)}
    items = sorted(scene.geometry.items(), key=lambda kv: rank.get(kv[0], len(rank)))
    return [(name, "MultiSurface" if name in surfaces else "Solid", mesh) for name, mesh in items]


def check_mesh_file(path) -> list[MeshCheck]:
    """:func:`check_mesh` for every building mesh of a GLB or OBJ file, in file order."""
    return [check_mesh(mesh, bid, kind) for bid, kind, mesh in building_meshes(path)]
