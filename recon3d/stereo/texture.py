"""Textures of the building models from the stereo images.

Roofs take their colours from the true orthophoto, straight down: a roof corner's
texture coordinate is its place in ``ortho.tif``. Each wall takes them from the image
that sees it largest and from the front (the projected area of its front face, in
pixels): a wall corner's texture coordinate is its projection into that image, so the
wall shows what the camera saw. Walls no image sees whole, from the front and at
least :data:`MIN_WALL_VIEW` of their frontal size, stay untextured, unless they are
low steps between the parts of a roof, which take the orthophoto's colours; ground
surfaces stay untextured.

The model's triangles are grouped per building by the image they take colours from;
each group becomes one textured primitive of ``buildings_textured.glb``
(:func:`recon3d.io.gltf.write_textured_glb`). Because texture coordinates are a
function of the position within a group, every group is welded; the groups of a
building meet at eaves and wall edges, where each keeps its own copy of the corner.

Given the DSM, a wall is only textured from an image whose line of sight to it the DSM
leaves clear: points on the wall are followed up their ray to the camera, and a wall more
than :data:`MAX_HIDDEN_SHARE` of whose points a tree, another building or its own
neighbour hides in an image is not textured from that image (the next best is taken).

Limits, stated so nobody relies on more: the test sees what the DSM holds, so a thin
occluder the DSM smooths away (a lamp post, a bare branch) still shows on a wall; each
texture is cut to the part the model uses and reduced to :data:`MAX_TEXTURE_SIZE`
pixels on its long side when larger, which is said in run.json and on the terminal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from recon3d.core.city import CityModel
from recon3d.core.raster import Raster
from recon3d.io.obj import highest_lod
from recon3d.stereo.ortho import OrthoImage, View, pixels_per_unit

__all__ = ["MAX_TEXTURE_SIZE", "Part", "Texture", "TexturedModel", "hidden", "texture_city"]

#: Longest side (pixels) of a texture: what every WebGL implementation takes (desktop
#: and mobile GPUs report MAX_TEXTURE_SIZE >= 4096), so the model opens in any viewer.
MAX_TEXTURE_SIZE = 4096

#: Least size of a wall in its image, as a share of its size seen from straight in
#: front at the same distance (the cosine of the angle off its normal: 81 degrees).
#: Nadir images see most walls more obliquely; their few rows of pixels would be
#: stretched over the whole wall, smeared with the ground beside it.
MIN_WALL_VIEW = 0.15

#: Walls up to this high (CRS height units) that no image sees well enough, the steps
#: between the parts of a roof and parapets, take the orthophoto's colours like the
#: roof around them, not the plain colour of untextured walls.
STEP_WALL_HEIGHT = 1.0

#: Largest share of a wall's sample points the DSM may hide from an image that textures it.
MAX_HIDDEN_SHARE = 0.25

#: Height (CRS units) the DSM must rise above a line of sight to hide what is behind it:
#: a stereo DSM blurs the foot of a wall over a cell or two, which must not hide the wall.
HIDING_HEIGHT = 1.0

#: Most samples along one line of sight (the march stops where the ray passes the DSM's top).
MAX_RAY_STEPS = 400

#: Pixels kept around the texture coordinates a crop of an image must hold: bilinear
#: sampling and mipmaps read the neighbours of the last texel.
CROP_MARGIN = 4


@dataclass
class Texture:
    """One image of the textured model.

    Attributes
    ----------
    name : str
        "ortho", or the name of the stereo image the walls come from.
    image : (h, w, 3) uint8
        RGB (panchromatic images repeated in the three bands).
    reduced : int
        Factor the source pixels were reduced by to fit :data:`MAX_TEXTURE_SIZE` (1: none).
    """

    name: str
    image: np.ndarray
    reduced: int = 1


@dataclass
class Part:
    """The triangles of one building that share a texture: one glTF primitive.

    Attributes
    ----------
    texture : int
        Index into :attr:`TexturedModel.textures`; -1 for untextured triangles.
    vertices : (n, 3) float64
        In the city model's local frame.
    uv : (n, 2) float32
        Texture coordinates, (0, 0) the top-left corner of the image, (1, 1) the
        bottom-right; zeros for untextured parts.
    faces : (m, 3) int64
        Triangles on ``vertices``, wound outward as the solid's.
    """

    texture: int
    vertices: np.ndarray
    uv: np.ndarray
    faces: np.ndarray


@dataclass
class TexturedModel:
    """The city model's highest-LoD solids as textured parts.

    Attributes
    ----------
    textures : list of Texture
    parts : dict of str to list of Part
        Per building id, its parts (buildings without a solid are left out).
    info : dict
        What run.json records: textured roofs and walls, reduced textures.
    """

    textures: list[Texture]
    parts: dict[str, list[Part]] = field(default_factory=dict)
    info: dict = field(default_factory=dict)


@dataclass
class _Triangles:
    """Every building's highest-LoD triangles, concatenated."""

    world: np.ndarray  # (n, 3) vertices in the CRS
    faces: np.ndarray  # (m, 3) into world
    kind: np.ndarray  # (m,) "RoofSurface", "WallSurface", ...
    surface: np.ndarray  # (m,) surface id, unique across buildings
    building: np.ndarray  # (m,) index into ids
    ids: list[str]
    local: np.ndarray  # (n, 3) vertices in the local frame


def _triangles(city: CityModel) -> _Triangles:
    origin = np.asarray(city.frame.origin, np.float64)
    verts, faces, kinds, surfaces, owners, ids = [], [], [], [], [], []
    n_vert = n_surf = 0
    for building in city.buildings:
        lod = highest_lod(building)
        if lod is None:
            continue
        solid = building.solids[lod]
        v, f, s = solid.mesh()
        verts.append(v)
        faces.append(f + n_vert)
        kinds.append(np.array(solid.semantics, dtype=object)[s] if len(s) else np.zeros(0, object))
        surfaces.append(s + n_surf)
        owners.append(np.full(len(f), len(ids)))
        ids.append(str(building.id))
        n_vert += len(v)
        n_surf += len(solid.semantics)
    if not ids:
        empty = np.zeros((0, 3))
        return _Triangles(empty, np.zeros((0, 3), np.int64), np.zeros(0, object), np.zeros(0, np.int64),
                          np.zeros(0, np.int64), [], empty)
    local = np.concatenate(verts)
    return _Triangles(local + origin, np.concatenate(faces).astype(np.int64), np.concatenate(kinds),
                      np.concatenate(surfaces), np.concatenate(owners), ids, local)


def _as_rgb(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8 of an (h, w, bands) image: float images (NaN nodata) stretched
    from their 0.1 to 99.9 percentile, one band repeated three times."""
    if image.dtype != np.uint8:
        finite = np.isfinite(image)
        lo, hi = np.percentile(image[finite], [0.1, 99.9]) if finite.any() else (0.0, 1.0)
        scaled = (np.nan_to_num(image, nan=lo) - lo) * (255.0 / max(hi - lo, 1e-9))
        image = np.clip(np.rint(scaled), 0, 255).astype(np.uint8)
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    return np.ascontiguousarray(image[:, :, :3])


def _fit(image: np.ndarray, max_size: int) -> tuple[np.ndarray, int]:
    """The image reduced by the smallest whole factor that fits ``max_size`` (area
    averaging), and that factor. Texture coordinates are fractions of the image, so
    they hold for the reduced image as they were."""
    import cv2

    factor = max(1, math.ceil(max(image.shape[:2]) / max_size))
    if factor == 1:
        return image, 1
    h, w = image.shape[:2]
    size = (max(1, round(w / factor)), max(1, round(h / factor)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), factor


def _signed_area(col: np.ndarray, row: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) signed pixel area of each projected triangle."""
    c, r = col[faces], row[faces]
    return 0.5 * ((c[:, 1] - c[:, 0]) * (r[:, 2] - r[:, 0]) - (c[:, 2] - c[:, 0]) * (r[:, 1] - r[:, 0]))


def _front_sign(view: View, centre: np.ndarray) -> float:
    """Sign of the projected area of a face seen from the front in ``view``: that of a
    small upward-facing triangle at ``centre``, which every aerial view sees from above
    (0 if it does not land)."""
    x, y, z = centre
    col, row = (np.asarray(a, np.float64) for a in
                view.project(np.array([x, x + 1.0, x]), np.array([y, y, y + 1.0]), np.full(3, z)))
    area = _signed_area(col, row, np.array([[0, 1, 2]]))[0]
    return float(np.sign(area)) if np.isfinite(area) else 0.0


def _wall_samples(tri: _Triangles, walls: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on the wall triangles, ``step`` out from the wall, and the surface of each.

    Each triangle gives its centroid and the three points halfway from it to its
    corners; ``step`` (a DSM cell) out along the outward normal, so that the wall's own
    edge cell of the DSM does not hide it.

    Returns
    -------
    points : (4 m, 3) float
    surface : (4 m,) int
    """
    corners = tri.world[tri.faces[walls]]
    if not len(corners):
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal[:, 2] = 0.0  # out of the wall, level (walls are vertical)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    centre = corners.mean(axis=1)
    points = np.concatenate([centre[:, None], 0.5 * (centre[:, None] + corners)], axis=1) + step * normal[:, None]
    return points.reshape(-1, 3), np.repeat(tri.surface[walls], 4)


def hidden(view: View, points: np.ndarray, dsm: Raster, *, hiding: float = HIDING_HEIGHT) -> np.ndarray:
    """(n,) bool: points whose line of sight to ``view`` passes under the DSM.

    The line of sight is found from the projection alone (any camera model): the
    horizontal shift per unit of height that keeps a point on the same pixel, from the
    projection's derivatives. Each ray is followed upwards a DSM cell at a time until it
    passes the DSM's highest cell; it is blocked where the DSM stands more than
    ``hiding`` above it. Points the view does not see at all (behind it) are hidden.

    Parameters
    ----------
    view : View
    points : (n, 3) float
        World coordinates (the DSM's CRS).
    dsm : Raster
    hiding : float
        CRS height units.
    """
    x, y, z = (points[:, k].astype(np.float64) for k in range(3))
    col, row = (np.asarray(a, np.float64) for a in view.project(x, y, z))
    derivatives = [view.project(x + dx, y + dy, z + dz) for dx, dy, dz in ((1, 0, 0), (0, 1, 0), (0, 0, 1))]
    (ex, nx), (ey, ny), (ez, nz) = ((np.asarray(c) - col, np.asarray(r) - row) for c, r in derivatives)
    det = ex * ny - ey * nx  # pixel motion per metre east and north; solve for the shift undoing a metre up
    with np.errstate(invalid="ignore", divide="ignore"):
        sx = (-ez * ny + ey * nz) / det
        sy = (-ex * nz + nx * ez) / det
    blocked = ~(np.isfinite(sx) & np.isfinite(sy))
    sx, sy = np.nan_to_num(sx), np.nan_to_num(sy)
    top = float(np.nanmax(dsm.data)) if np.isfinite(dsm.data).any() else -np.inf
    cell = dsm.resolution
    dt = np.minimum(cell / np.maximum(np.hypot(sx, sy), 1e-9), 2.0 * cell)  # up per step: a cell sideways at most
    steps = np.clip(np.ceil((top - z) / dt), 0, MAX_RAY_STEPS).astype(np.int64)
    for k in range(1, int(steps.max(initial=0)) + 1):
        live = np.flatnonzero((k <= steps) & ~blocked)
        if not len(live):
            break
        t = k * dt[live]
        ground = dsm.sample(x[live] + t * sx[live], y[live] + t * sy[live], bilinear=False)
        blocked[live] |= np.nan_to_num(ground, nan=-np.inf) > z[live] + t + hiding
    return blocked


def _best_views(tri: _Triangles, walls: np.ndarray, views: list[View],
                dsm: Raster | None = None) -> tuple[np.ndarray, list]:
    """Per wall surface, the view that sees it largest from the front, with all its
    corners on the image, at least :data:`MIN_WALL_VIEW` of its frontal size and (given
    the DSM) at most :data:`MAX_HIDDEN_SHARE` of it hidden (-1: none), and every view's
    projection of the vertices."""
    n_surf = int(tri.surface.max()) + 1 if len(tri.surface) else 0
    best = np.full(n_surf, -1)
    best_area = np.zeros(n_surf)
    projections = []
    centre = np.nanmedian(tri.world, axis=0) if len(tri.world) else np.zeros(3)
    wall_faces, wall_surface = tri.faces[walls], tri.surface[walls]
    corners = tri.world[wall_faces]
    world_area = np.bincount(wall_surface, minlength=n_surf, weights=0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1))
    samples = _wall_samples(tri, walls, dsm.resolution) if dsm is not None else None
    for k, view in enumerate(views):
        col, row = (np.asarray(a, np.float64) for a in view.project(tri.world[:, 0], tri.world[:, 1], tri.world[:, 2]))
        projections.append((col, row))
        sign = _front_sign(view, centre)
        if sign == 0 or not len(wall_faces):
            continue
        h, w = view.image.shape[:2]
        on = np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
        area = np.bincount(wall_surface, weights=sign * _signed_area(col, row, wall_faces), minlength=n_surf)
        off = np.bincount(wall_surface, weights=(~on[wall_faces].all(axis=1)).astype(np.float64), minlength=n_surf)
        frontal = world_area * pixels_per_unit(view, *centre) ** 2
        better = (off == 0) & (area > best_area) & (area >= MIN_WALL_VIEW * frontal)
        if samples is not None and better.any():
            better &= _hidden_share(view, *samples, better, dsm) <= MAX_HIDDEN_SHARE
        best[better], best_area[better] = k, area[better]
    return best, projections


def _hidden_share(view: View, points: np.ndarray, surface: np.ndarray, candidates: np.ndarray,
                  dsm: Raster) -> np.ndarray:
    """(n_surf,) share of each candidate wall surface's sample points (:func:`_wall_samples`)
    the DSM hides from ``view``; 0 for the other surfaces, whose rays are not followed."""
    pick = candidates[surface]
    n_surf = len(candidates)
    count = np.bincount(surface[pick], minlength=n_surf)
    blocked = np.bincount(surface[pick], weights=hidden(view, points[pick], dsm).astype(np.float64), minlength=n_surf)
    return blocked / np.maximum(count, 1)


def _low_walls(tri: _Triangles) -> np.ndarray:
    """(m,) bool: triangles of surfaces spanning at most :data:`STEP_WALL_HEIGHT` in height."""
    z = tri.world[tri.faces, 2]
    n = int(tri.surface.max()) + 1 if len(tri.surface) else 0
    top, bottom = np.full(n, -np.inf), np.full(n, np.inf)
    np.maximum.at(top, tri.surface, z.max(axis=1))
    np.minimum.at(bottom, tri.surface, z.min(axis=1))
    return (top - bottom)[tri.surface] <= STEP_WALL_HEIGHT


def _crop(image: np.ndarray, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, int, int]:
    """The part of ``image`` holding the pixel coordinates (plus :data:`CROP_MARGIN`),
    and its first column and row."""
    h, w = image.shape[:2]
    c0 = max(0, int(np.floor(col.min())) - CROP_MARGIN)
    r0 = max(0, int(np.floor(row.min())) - CROP_MARGIN)
    c1 = min(w, int(np.ceil(col.max())) + CROP_MARGIN + 1)
    r1 = min(h, int(np.ceil(row.max())) + CROP_MARGIN + 1)
    return image[r0:r1, c0:c1], c0, r0


def _parts(tri: _Triangles, texture: np.ndarray, uvs: dict[int, np.ndarray], n_textures: int) -> dict[str, list[Part]]:
    """Each building's triangles grouped by texture, each group on its own vertices."""
    parts: dict[str, list[Part]] = {}
    order = np.lexsort((texture, tri.building))
    keys = tri.building[order] * (n_textures + 1) + texture[order] + 1
    starts = np.r_[0, np.flatnonzero(np.diff(keys)) + 1, len(order)] if len(order) else np.zeros(1, np.int64)
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        group = order[a:b]
        k = int(texture[group[0]])
        used, faces = np.unique(tri.faces[group], return_inverse=True)
        coords = uvs[k][used] if k >= 0 else np.zeros((len(used), 2))
        part = Part(k, tri.local[used], coords.astype(np.float32), faces.reshape(-1, 3).astype(np.int64))
        parts.setdefault(tri.ids[int(tri.building[group[0]])], []).append(part)
    return parts


def texture_city(
    city: CityModel, views: list[View], ortho: OrthoImage | None, *, dsm: Raster | None = None,
    max_size: int = MAX_TEXTURE_SIZE,
) -> TexturedModel:
    """The city's highest-LoD solids, their roofs textured from ``ortho`` and their walls
    from ``views`` (see the module's description).

    Parameters
    ----------
    city : CityModel
    views : list of View
        The stereo images and their projections (world CRS coordinates to pixels).
    ortho : OrthoImage, optional
        The true orthophoto; without it roofs are untextured.
    dsm : Raster, optional
        The surface walls are tested against for occlusion (see :func:`hidden`);
        without it every front-facing view counts.
    max_size : int
        Longest side of a texture, pixels.

    Returns
    -------
    TexturedModel
    """
    tri = _triangles(city)
    roofs = tri.kind == "RoofSurface"
    walls = tri.kind == "WallSurface"
    best, projections = _best_views(tri, walls, views, dsm)
    texture = np.full(len(tri.faces), -1, np.int64)  # of each triangle: an index into textures, -1 none
    textures: list[Texture] = []
    uvs: dict[int, np.ndarray] = {}  # per texture, (n, 2) coordinates of every vertex
    wall_view = np.where(walls, best[tri.surface] if len(best) else -1, -1)
    from_ortho = -2  # the orthophoto's texture index, once it has one
    if ortho is not None and roofs.any():
        image, reduced = _fit(_as_rgb(np.moveaxis(ortho.data, 0, -1)), max_size)
        t = ortho.transform
        rows, cols = ortho.data.shape[1:]
        uvs[len(textures)] = np.column_stack([(tri.world[:, 0] - t.c) / t.a / cols, (tri.world[:, 1] - t.f) / t.e / rows])
        from_ortho = len(textures)
        texture[roofs | (walls & (wall_view < 0) & _low_walls(tri))] = from_ortho
        textures.append(Texture("ortho", image, reduced))
    for k, view in enumerate(views):
        mine = wall_view == k
        if not mine.any():
            continue
        col, row = projections[k]
        used = np.unique(tri.faces[mine])
        crop, c0, r0 = _crop(_as_rgb(view.image), col[used], row[used])
        image, reduced = _fit(crop, max_size)
        h, w = crop.shape[:2]
        # pixel centres are at whole coordinates; texture coordinates run over pixel edges
        uvs[len(textures)] = np.column_stack([(col - c0 + 0.5) / w, (row - r0 + 0.5) / h])
        texture[mine] = len(textures)
        textures.append(Texture(view.name, image, reduced))
    model = TexturedModel(textures, _parts(tri, texture, uvs, len(textures)))
    model.info = {
        "roof_triangles_textured": int(np.count_nonzero(roofs & (texture >= 0))),
        "wall_surfaces": len(np.unique(tri.surface[walls])),
        "wall_surfaces_textured": len(np.unique(tri.surface[walls & (texture >= 0)])),
        "wall_surfaces_from_ortho": len(np.unique(tri.surface[walls & (texture == from_ortho)])),
        "textures": [{"name": t.name, "size": [int(t.image.shape[1]), int(t.image.shape[0])], "reduced": t.reduced}
                     for t in textures],
    }
    return model
