"""Procedural test cities with exact ground truth.

A :class:`SyntheticCity` is terrain (gentle relief, flat, a 10 % slope or hills), a grid
of streets and lots (regular, dense or sparse), one building per lot (flat, shed, gable,
hip and pyramid roofs on rectangles; flat L and T plans; one courtyard building) and
trees (ellipsoid or cone crowns on trunks) beside the buildings or over their roofs,
and optionally groves: clusters of touching crowns covering 75 m2 or more, which a
detector must not take for a building.
Everything is a triangle mesh in a local metric frame (z up, float32-safe
coordinates); ``city.origin`` is added to get world coordinates in ``city.crs``
(UTM-sized by default, so consumers are tested against the float32 pitfall).

The truth is exact: :func:`truth_dsm` casts vertical rays at the mesh,
:func:`truth_dtm` evaluates the piecewise-linear terrain, and each building keeps
its footprint, roof type, eave and ridge heights and its LoD2 solid.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import shapely
import shapely.affinity
import trimesh
from affine import Affine

from recon3d.buildings.lod import clean_footprint, lod1_solid
from recon3d.core.city import Solid
from recon3d.core.geo import LocalFrame

log = logging.getLogger(__name__)

__all__ = [
    "LAYOUTS",
    "MATERIALS",
    "TERRAINS",
    "TREES",
    "BuildingTruth",
    "Layout",
    "StreetGrid",
    "SyntheticCity",
    "Terrain",
    "TreeTruth",
    "cell_centres",
    "checkpoints",
    "make_city",
    "row_blocks",
    "truth_disparity",
    "truth_dsm",
    "truth_dtm",
]

#: Surface materials, the index stored per triangle in ``SyntheticCity.face_material``.
MATERIALS = ("ground", "tiles", "gravel", "wall", "foliage", "bark")
GROUND, TILES, GRAVEL, WALL, FOLIAGE, BARK = range(len(MATERIALS))

#: Roof types of the buildings, in the order every city gets them first.
ROOF_TYPES = ("flat", "shed", "gable", "hip", "pyramid")
#: How often each roof type is drawn once every type is present.
_ROOF_WEIGHTS = (0.3, 0.1, 0.3, 0.2, 0.1)

#: Terrain kinds of :func:`make_city`.
TERRAINS = ("gentle", "flat", "slope", "hilly", "mountain")


@dataclass(frozen=True)
class Layout:
    """How densely a city is built: street pitch and width, setback, share of lots built."""

    pitch: float
    street: float
    setback: float
    built: float


#: Building layouts of :func:`make_city`: the regular grid, a dense one of narrow
#: streets and small lots, and a sparse one where most lots stay open ground.
LAYOUTS = {
    "regular": Layout(pitch=36.0, street=8.0, setback=2.0, built=1.0),
    "dense": Layout(pitch=25.0, street=6.0, setback=1.0, built=1.0),
    "sparse": Layout(pitch=36.0, street=8.0, setback=2.0, built=0.4),
    "none": Layout(pitch=36.0, street=8.0, setback=2.0, built=0.0),
}

#: Tree placements of :func:`make_city`.
TREES = ("none", "beside", "over")

_TERRAIN_SPACING = 2.5
_DEFAULT_ORIGIN = (500000.0, 5400000.0, 0.0)


def _rng(seed: int, stream: int) -> np.random.Generator:
    """An independent generator per purpose, so adding trees does not move buildings."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), stream]))


# --------------------------------------------------------------------------- terrain


@dataclass
class Terrain:
    """A height grid triangulated along one diagonal per cell (the terrain mesh).

    Parameters
    ----------
    x0, y0 : float
        Local coordinates of grid node (0, 0).
    spacing : float
        Node spacing in metres.
    z : (ny, nx) float64
        Local heights of the nodes; ``z[j, i]`` is at ``(x0 + i*spacing, y0 + j*spacing)``.
    """

    x0: float
    y0: float
    spacing: float
    z: np.ndarray

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Exact local height of the terrain mesh at local (x, y), same shape as ``x``.

        Cells are split along the diagonal from node (i, j) to (i+1, j+1), as in
        :meth:`mesh`, so this equals a vertical ray cast on the mesh. Points outside
        the grid are clamped to its edge.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        ny, nx = self.z.shape
        fx = np.clip((x - self.x0) / self.spacing, 0, nx - 1)
        fy = np.clip((y - self.y0) / self.spacing, 0, ny - 1)
        i = np.minimum(np.floor(fx).astype(np.int64), nx - 2)
        j = np.minimum(np.floor(fy).astype(np.int64), ny - 2)
        u, v = fx - i, fy - j
        z00, z10 = self.z[j, i], self.z[j, i + 1]
        z01, z11 = self.z[j + 1, i], self.z[j + 1, i + 1]
        lower = z00 + u * (z10 - z00) + v * (z11 - z10)
        upper = z00 + v * (z01 - z00) + u * (z11 - z01)
        return np.where(u >= v, lower, upper)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (ny*nx, 3) float64 and triangles (2*(ny-1)*(nx-1), 3) int64, upward."""
        ny, nx = self.z.shape
        xs = self.x0 + self.spacing * np.arange(nx)
        ys = self.y0 + self.spacing * np.arange(ny)
        gx, gy = np.meshgrid(xs, ys)
        vertices = np.column_stack([gx.ravel(), gy.ravel(), self.z.ravel()])
        idx = np.arange(ny * nx).reshape(ny, nx)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        # (a, b, d) is the u >= v half, (a, d, c) the other: both counter-clockwise from above
        faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
        return vertices, faces


def _make_terrain(rng: np.random.Generator, size: float, margin: float, kind: str = "gentle") -> Terrain:
    """Terrain about 50 m above the datum at the city centre.

    ``"gentle"``: smooth random hills of a few metres on a slope of about 1 %;
    ``"flat"``: a level plane; ``"slope"``: a 10 % incline in a random direction with
    hills of a metre; ``"hilly"``: hills and valleys of 6 to 15 m, about 100 m across;
    ``"mountain"``: peaks and valleys of a fifth of the area's width, slopes of 30 to
    60 % and steeper on their flanks.
    """
    if kind not in TERRAINS:
        raise ValueError(f"terrain {kind!r} is not one of {TERRAINS}")
    n = int(math.ceil((size + 2 * margin) / _TERRAIN_SPACING)) + 1
    x0 = y0 = -margin
    coords = x0 + _TERRAIN_SPACING * np.arange(n)
    gx, gy = np.meshgrid(coords, coords)
    z = np.full(gx.shape, 50.0)
    if kind == "flat":
        return Terrain(x0, y0, _TERRAIN_SPACING, z)
    if kind == "mountain":
        span = max(size, 200.0)
        for _ in range(int(rng.integers(3, 6))):
            cx, cy = rng.uniform(-0.1 * size, 1.1 * size, size=2)
            sigma = rng.uniform(0.18, 0.3) * span
            peak = rng.choice([-1.0, 1.0], p=[0.3, 0.7]) * rng.uniform(0.6, 1.0) * sigma  # slopes 0.35-0.6
            z += peak * np.exp(-((gx - cx) ** 2 + (gy - cy) ** 2) / (2 * sigma**2))
        z += 50.0 - float(Terrain(x0, y0, _TERRAIN_SPACING, z).height(np.array(size / 2), np.array(size / 2)))
        return Terrain(x0, y0, _TERRAIN_SPACING, z)
    if kind == "slope":
        angle = rng.uniform(0, 2 * math.pi)
        slope, amp, count, scale = 0.10 * np.array([math.cos(angle), math.sin(angle)]), 1.0, (3, 5), (0.2, 0.4)
    elif kind == "hilly":
        slope, amp, count, scale = rng.uniform(-0.02, 0.02, size=2), 15.0, (6, 10), (0.08, 0.16)
    else:
        slope, amp, count, scale = rng.uniform(-0.012, 0.012, size=2), 3.0, (4, 7), (0.2, 0.45)
    z += slope[0] * (gx - size / 2) + slope[1] * (gy - size / 2)
    extent = max(size, 100.0) if kind != "hilly" else max(size, 600.0)
    for _ in range(int(rng.integers(*count))):
        cx, cy = rng.uniform(-0.2 * size, 1.2 * size, size=2)
        sigma = rng.uniform(*scale) * extent
        height = rng.uniform(-amp, amp) if kind != "hilly" else rng.choice([-1, 1]) * rng.uniform(6.0, amp)
        z += height * np.exp(-((gx - cx) ** 2 + (gy - cy) ** 2) / (2 * sigma**2))
    if kind != "gentle":  # the same heights at the centre whatever the relief
        z += 50.0 - float(Terrain(x0, y0, _TERRAIN_SPACING, z).height(np.array(size / 2), np.array(size / 2)))
    return Terrain(x0, y0, _TERRAIN_SPACING, z)


# --------------------------------------------------------------------------- streets


@dataclass(frozen=True)
class StreetGrid:
    """Streets every ``pitch`` metres from ``start`` (local x and y), ``width`` wide, on
    ``n + 1`` lines each way; the ``n`` x ``n`` lots lie between them."""

    start: float
    pitch: float
    width: float
    n: int

    def is_street(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Boolean mask, same shape as ``x``: True on the street surface (local x, y)."""
        end = self.start + self.n * self.pitch + self.width

        def on_line(c):
            m = np.mod(c - self.start, self.pitch)
            return m < self.width

        inside = (x >= self.start) & (x <= end) & (y >= self.start) & (y <= end)
        return inside & (on_line(np.asarray(x)) | on_line(np.asarray(y)))

    def lot(self, i: int, j: int) -> shapely.Polygon:
        """Lot (i, j) as a local polygon (the square between four street lines)."""
        x = self.start + i * self.pitch + self.width
        y = self.start + j * self.pitch + self.width
        s = self.pitch - self.width
        return shapely.box(x, y, x + s, y + s)


def _street_grid(size: float, layout: Layout = LAYOUTS["regular"]) -> StreetGrid:
    n = round((size - layout.street) / layout.pitch)
    pitch = (size - layout.street) / max(n, 1)
    if n < 1 or pitch < layout.pitch * 5 / 6:
        raise ValueError(f"a city of {size} m has no room for one lot (at least {layout.pitch + layout.street:.0f} m)")
    return StreetGrid(0.0, pitch, layout.street, n)


# --------------------------------------------------------------------------- buildings


@dataclass
class BuildingTruth:
    """One building of a synthetic city and its exact geometry.

    Attributes
    ----------
    id : str
    plan : str
        "rectangle", "L", "T" or "courtyard".
    roof_type : str
        One of "flat", "shed", "gable", "hip", "pyramid".
    footprint : shapely.Polygon
        Outline in world coordinates (counter-clockwise, courtyard as a hole).
    footprint_local : shapely.Polygon
        The same in local coordinates.
    ground_z : float
        World height of the lowest terrain point under the footprint (where walls start).
    eave_z, ridge_z : float
        World heights of the lowest and highest roof points.
    lod1_z : float
        Height of the LoD1 prism with the same volume as the building.
    top : (3,) float64
        World coordinates of the highest roof point (the roof check point).
    solid : Solid
        The LoD2 truth solid in local coordinates, with semantic surfaces.
    parts : tuple of (str, Solid, shapely.Polygon)
        Superstructures and recesses of the roof (``make_city(superstructures=True)``):
        kind ("box": a stair house or plant room on a flat roof, "dormer" on a
        slope, "well": the floor of a light well cut into a flat roof), the part's
        solid (local; touching or inside ``solid``, not merged with it) and its plan
        (world). Empty without superstructures.
    """

    id: str
    plan: str
    roof_type: str
    footprint: shapely.Polygon
    footprint_local: shapely.Polygon
    ground_z: float
    eave_z: float
    ridge_z: float
    lod1_z: float
    top: np.ndarray
    solid: Solid
    parts: tuple = ()

    @property
    def height(self) -> float:
        """Ridge height above the ground, metres."""
        return self.ridge_z - self.ground_z


def _rect_solid(kind: str, a: float, b: float, zb: float, ze: float, zr: float) -> Solid:
    """A rectangular building ``[-a, a] x [-b, b]`` (ridge along x) with roof ``kind``.

    Vertices 0-3 are the base corners (counter-clockwise from above), 4-7 the eave
    corners; gable and hip add ridge ends 8, 9, pyramid an apex 8. Surfaces are
    oriented outward.
    """
    corners = np.array([[-a, -b], [a, -b], [a, b], [-a, b]])
    base = np.column_stack([corners, np.full(4, zb)])
    top_z = np.array([ze, ze, zr, zr]) if kind == "shed" else np.full(4, ze)
    eave = np.column_stack([corners, top_z])
    extra: list[list[float]] = []
    walls = [[0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    if kind in ("flat", "shed"):
        roofs = [[4, 5, 6, 7]]
    elif kind == "gable":
        extra = [[-a, 0, zr], [a, 0, zr]]
        walls = [[0, 1, 5, 4], [1, 2, 6, 9, 5], [2, 3, 7, 6], [3, 0, 4, 8, 7]]
        roofs = [[4, 5, 9, 8], [6, 7, 8, 9]]
    elif kind == "hip":
        extra = [[-a + b, 0, zr], [a - b, 0, zr]]
        roofs = [[4, 5, 9, 8], [5, 6, 9], [6, 7, 8, 9], [7, 4, 8]]
    elif kind == "pyramid":
        extra = [[0, 0, zr]]
        roofs = [[4, 5, 8], [5, 6, 8], [6, 7, 8], [7, 4, 8]]
    else:
        raise ValueError(f"unknown roof type {kind!r}")
    vertices = np.concatenate([base, eave, np.reshape(extra, (-1, 3))])
    rings = [[3, 2, 1, 0], *walls, *roofs]
    surfaces = [[np.array(r)] for r in rings]
    semantics = ["GroundSurface"] + ["WallSurface"] * len(walls) + ["RoofSurface"] * len(roofs)
    return Solid(vertices, surfaces, semantics)


def _place(solid: Solid, angle: float, center: np.ndarray) -> Solid:
    """The solid rotated by ``angle`` (radians, about z) and moved to local ``center`` (x, y)."""
    c, s = math.cos(angle), math.sin(angle)
    v = solid.vertices.copy()
    v[:, :2] = v[:, :2] @ np.array([[c, s], [-s, c]]) + center
    return Solid(v, solid.surfaces, solid.semantics)


def _plan_polygon(
    plan: str, roof: str, rng: np.random.Generator, room: float
) -> tuple[shapely.Polygon, float, float]:
    """A footprint centred on (0, 0) before rotation; returns it and its half-sizes (a, b).

    Rectangles are longer along x (a >= b); a hip roof gets ``b <= 0.75 a`` so its
    ridge has a length, a pyramid roof a square.
    """
    if plan == "rectangle":
        length = rng.uniform(10.0, room)
        width = rng.uniform(8.0, min(length, 16.0))
        if roof == "hip":
            width = min(width, 0.75 * length)
        elif roof == "pyramid":
            width = length = min(length, 18.0)
        return shapely.box(-length / 2, -width / 2, length / 2, width / 2), length / 2, width / 2
    if plan == "courtyard":
        s = rng.uniform(0.8, 1.0) * room
        h = rng.uniform(0.3, 0.4) * s
        outer = shapely.box(-s / 2, -s / 2, s / 2, s / 2)
        return outer.difference(shapely.box(-h / 2, -h / 2, h / 2, h / 2)), s / 2, s / 2
    s = rng.uniform(0.8, 1.0) * room
    w = rng.uniform(7.0, 9.0)
    if plan == "L":
        poly = shapely.union(shapely.box(0, 0, s, w), shapely.box(0, 0, w, s))
    elif plan == "T":
        stem = shapely.box((s - w) / 2, 0, (s + w) / 2, s)
        poly = shapely.union(shapely.box(0, s - w, s, s), stem)
    else:
        raise ValueError(f"unknown plan {plan!r}")
    return shapely.affinity.translate(poly, -s / 2, -s / 2), s / 2, s / 2


def _ground_range(terrain: Terrain, poly: shapely.Polygon) -> tuple[float, float]:
    """(min, max) local terrain height over a polygon (outline every 0.25 m and grid nodes)."""
    rings = [poly.exterior, *poly.interiors]
    pts = [shapely.line_interpolate_point(r, np.arange(0, r.length, 0.25)) for r in rings]
    xy = np.concatenate([shapely.get_coordinates(p) for p in pts])
    ny, nx = terrain.z.shape
    gx = terrain.x0 + terrain.spacing * np.arange(nx)
    gy = terrain.y0 + terrain.spacing * np.arange(ny)
    minx, miny, maxx, maxy = poly.bounds
    sx, sy = gx[(gx >= minx) & (gx <= maxx)], gy[(gy >= miny) & (gy <= maxy)]
    if len(sx) and len(sy):
        mx, my = np.meshgrid(sx, sy)
        inside = shapely.contains_xy(poly, mx, my)
        xy = np.concatenate([xy, np.column_stack([mx[inside], my[inside]])])
    z = terrain.height(xy[:, 0], xy[:, 1])
    return float(z.min()), float(z.max())


def _make_building(
    bid: str,
    plan: str,
    roof: str,
    lot: shapely.Polygon,
    terrain: Terrain,
    frame: LocalFrame,
    rng: np.random.Generator,
    setback: float = 2.0,
    parts_rng: np.random.Generator | None = None,
) -> BuildingTruth:
    """One building inside ``lot`` (local), standing on the terrain, at most 25 m high
    above its lowest ground (less where the ground under it is steep); with
    ``parts_rng``, maybe a superstructure or a light well (:func:`_roof_parts`)."""
    inner = lot.buffer(-setback, join_style="mitre")
    room = min(inner.bounds[2] - inner.bounds[0], inner.bounds[3] - inner.bounds[1])
    center = np.array(lot.centroid.coords[0])
    for attempt in range(50):
        poly0, a, b = _plan_polygon(plan, roof, rng, room)
        angle = 0.0 if attempt > 40 or rng.random() < 0.4 else rng.uniform(-0.35, 0.35)
        turned = shapely.affinity.rotate(poly0, angle, use_radians=True, origin=(0, 0))
        poly = shapely.affinity.translate(turned, *center)
        if inner.contains(poly):
            break
    else:  # pragma: no cover - the axis-aligned attempts always fit
        raise RuntimeError(f"building {bid} does not fit its lot")
    zmin, zmax = _ground_range(terrain, poly)
    rise = _roof_rise(roof, a, b, rng)
    eave_h = rng.uniform(4.5, max(5.0, 25.0 - rise - (zmax - zmin)))
    zb, ze = zmin, zmax + eave_h
    zr = ze + rise
    world_poly = shapely.affinity.translate(poly, frame.origin[0], frame.origin[1])
    parts, well, added = ((), None, 0.0)
    if parts_rng is not None:
        parts, well, added = _roof_parts(roof, poly, angle, center, (a, b), (zb, ze, zr), frame, parts_rng)
    if roof == "flat":
        fp = clean_footprint(world_poly if well is None else world_poly.difference(well), 1e-6)
        solid = lod1_solid(fp, zb + frame.origin[2], ze + frame.origin[2], frame)
    else:
        solid = _place(_rect_solid(roof, a, b, zb, ze, zr), angle, center)
    top = _roof_top(roof, poly, angle, center, a, b, ze, zr)
    boxes = [(float(p.vertices[:, 2].max()), plan) for kind, p, plan in parts if kind == "box"]
    if boxes:  # the highest stair house is the highest point
        zr, box_plan = max(boxes, key=lambda t: t[0])
        c = box_plan.centroid
        top = np.array([c.x - frame.origin[0], c.y - frame.origin[1], zr])
    elif well is not None and well.contains(shapely.Point(*(top[:2] + frame.origin[:2]))):
        p = world_poly.difference(well).representative_point()
        top = np.array([p.x - frame.origin[0], p.y - frame.origin[1], ze])
    volume = float(solid.to_trimesh().volume) + added
    oz = frame.origin[2]
    return BuildingTruth(
        id=bid,
        plan=plan,
        roof_type=roof,
        footprint=shapely.orient_polygons(world_poly),
        footprint_local=shapely.orient_polygons(poly),
        ground_z=zb + oz,
        eave_z=ze + oz,
        ridge_z=zr + oz,
        lod1_z=zb + volume / poly.area + oz,
        top=frame.to_world(top[None])[0],
        solid=solid,
        parts=parts,
    )


def _roof_parts(roof, poly, angle, center, half, heights, frame, rng):
    """Roof parts for seven buildings in ten, one to three each, 1 m apart at least:
    on a flat roof stair houses and plant rooms (1.5-5 m sides, 1.5-3 m high) and at
    most one light well (2-5 m sides, its floor 3-6 m down); on a gable or shed roof
    dormers (1.5-4 m wide, 1.5-3.5 m deep up the slope, their flat tops meeting it;
    on either side of a gable). Hip and pyramid roofs get none.

    Parameters
    ----------
    roof : str
    poly : shapely.Polygon
        The footprint, local.
    angle : float
        The building's rotation (radians); ``center`` (2,) its local position.
    half : (a, b)
        Half-sizes of a rectangular building (ridge along its x).
    heights : (zb, ze, zr)
        Local floor, eave and ridge heights.
    frame : LocalFrame
    rng : numpy.random.Generator

    Returns
    -------
    parts : tuple of (kind, Solid, shapely.Polygon)
        See :attr:`BuildingTruth.parts`.
    well : shapely.Polygon or None
        The light well's plan (world), to cut out of the roof.
    volume : float
        Volume (m3) the parts add to the building (the well's floor; the boxes and
        dormers above the roof).
    """
    if rng.random() >= 0.7 or roof in ("hip", "pyramid"):
        return (), None, 0.0
    parts, well, volume = [], None, 0.0
    for _ in range(int(rng.integers(1, 4))):
        if roof == "flat":
            part = _flat_roof_part(poly, angle, half, heights, frame, rng, well is None)
        else:
            part = _dormer(roof, angle, center, half, heights, frame, rng)
        if part is None or any(part[0][2].distance(p[2]) < 1.0 for p in parts):
            continue
        parts.append(part[0])
        volume += part[1]
        if part[0][0] == "well":
            well = part[0][2]
    return tuple(parts), well, volume


def _flat_roof_part(poly, angle, half, heights, frame, rng, well_allowed):
    """((kind, solid, plan), volume) of a stair house or a light well, or None."""
    zb, ze, _ = heights
    ox, oy, oz = frame.origin
    kind = "well" if well_allowed and rng.random() < 0.3 else "box"
    room = poly.buffer(-2.0 if kind == "well" else -1.0, join_style="mitre")
    if room.is_empty:
        return None
    x0, y0, x1, y1 = room.bounds
    for _ in range(40):
        w, d = rng.uniform(2.0, 5.0, 2) if kind == "well" else rng.uniform(1.5, 5.0, 2)
        c = rng.uniform((x0, y0), (x1, y1))
        rect = shapely.affinity.rotate(shapely.box(-w / 2, -d / 2, w / 2, d / 2), angle, use_radians=True, origin=(0, 0))
        rect = shapely.affinity.translate(rect, *c)
        if room.contains(rect):
            break
    else:
        return None
    plan = shapely.orient_polygons(shapely.affinity.translate(rect, ox, oy))
    if kind == "box":
        h = rng.uniform(1.5, 3.0)
        return (kind, lod1_solid(plan, ze - 0.5 + oz, ze + h + oz, frame), plan), plan.area * h
    floor = max(zb + 2.5, ze - rng.uniform(3.0, 6.0))
    return (kind, lod1_solid(plan, zb + oz, floor + oz, frame), plan), plan.area * (floor - zb)


def _dormer(roof, angle, center, half, heights, frame, rng):
    """(("dormer", solid, plan), volume) of a flat-topped dormer on a slope, or None."""
    (a, b), (_, ze, zr) = half, heights
    ox, oy, oz = frame.origin
    dw, dd = rng.uniform(1.5, 4.0), min(rng.uniform(1.5, 3.5), b - 2.0)
    if dd < 1.5:
        return None
    xc = rng.uniform(-a + 1.0 + dw / 2, a - 1.0 - dw / 2)
    ya = -b + rng.uniform(0.5, 1.5)
    run = b if roof == "gable" else 2 * b  # the slope's horizontal length from the eave

    def slope_z(y):
        return ze + (zr - ze) * (y + b) / run

    top = slope_z(ya + dd)
    rect = shapely.box(xc - dw / 2, ya, xc + dw / 2, ya + dd)
    if roof == "gable" and rng.random() < 0.5:  # the back slope
        rect = shapely.affinity.scale(rect, 1.0, -1.0, origin=(0, 0))
    rect = shapely.affinity.rotate(rect, angle, use_radians=True, origin=(0, 0))
    plan = shapely.orient_polygons(shapely.affinity.translate(rect, center[0] + ox, center[1] + oy))
    solid = lod1_solid(plan, ze - 1.0 + oz, top + oz, frame)
    return ("dormer", solid, plan), dw * dd * (top - slope_z(ya)) / 2


def _roof_rise(roof: str, a: float, b: float, rng: np.random.Generator) -> float:
    """Height of the ridge above the eaves for a roof over half-sizes (a, b)."""
    if roof == "flat":
        return 0.0
    if roof == "shed":
        return 2 * b * math.tan(math.radians(rng.uniform(8.0, 18.0)))
    return min(a, b) * math.tan(math.radians(rng.uniform(25.0, 42.0)))


def _roof_top(roof, poly, angle, center, a, b, ze, zr) -> np.ndarray:
    """Local (3,) highest roof point: the ridge middle, the apex, the middle of a flat
    roof, or for a shed roof the middle of its high edge moved 0.5 m inward (off the wall)."""
    if roof == "flat":
        p = poly.centroid if poly.contains(poly.centroid) else poly.representative_point()
        return np.array([p.x, p.y, ze])
    local = np.array([0.0, 0.0, zr])
    if roof == "shed":
        local = np.array([0.0, b - 0.5, zr - 0.5 * (zr - ze) / (2 * b)])
    c, s = math.cos(angle), math.sin(angle)
    xy = local[:2] @ np.array([[c, s], [-s, c]]) + center
    return np.array([xy[0], xy[1], local[2]])


def _building_kinds(n: int, rng: np.random.Generator) -> list[tuple[str, str]]:
    """(plan, roof) per building: every roof type, an L, a T and a courtyard first."""
    first = [("rectangle", r) for r in ROOF_TYPES]
    first += [("courtyard", "flat"), ("L", "flat"), ("T", "flat")]
    extra = rng.choice(len(ROOF_TYPES), size=max(0, n - len(first)), p=_ROOF_WEIGHTS)
    rest = [("rectangle", ROOF_TYPES[int(k)]) for k in extra]
    kinds = first[:n] + rest
    order = rng.permutation(len(kinds))
    return [kinds[i] for i in order]


# --------------------------------------------------------------------------- trees


@dataclass
class TreeTruth:
    """A tree: trunk and an ellipsoid (deciduous) or cone (conifer) crown.

    ``x``, ``y`` are local; ``ground_z`` and ``top_z`` world heights.
    """

    id: str
    x: float
    y: float
    ground_z: float
    top_z: float
    crown_radius: float
    crown: str


def _tree_meshes(tree: TreeTruth, oz: float) -> list[tuple[trimesh.Trimesh, int]]:
    """(mesh, material) of the trunk and the crown, in local coordinates."""
    g, top, r = tree.ground_z - oz, tree.top_z - oz, tree.crown_radius
    depth = (top - g) * (0.75 if tree.crown == "cone" else 0.6)
    base = top - depth
    axis = [[tree.x, tree.y, g - 0.5], [tree.x, tree.y, base + 0.3]]
    trunk = trimesh.creation.cylinder(radius=0.25, segment=axis, sections=8)
    if tree.crown == "cone":
        crown = trimesh.creation.cone(radius=r, height=depth, sections=16)
        crown.apply_translation([tree.x, tree.y, base])
    else:
        crown = trimesh.creation.icosphere(subdivisions=2)
        crown.apply_scale([r, r, depth / 2])
        crown.apply_translation([tree.x, tree.y, base + depth / 2])
    return [(trunk, BARK), (crown, FOLIAGE)]


def _make_trees(
    rng: np.random.Generator,
    size: float,
    terrain: Terrain,
    footprints: list[shapely.Polygon],
    oz: float,
) -> list[TreeTruth]:
    """Trees on free ground, clear of buildings (crown + 1.5 m) and of each other."""
    blocked = shapely.union_all(footprints) if footprints else shapely.Polygon()
    shapely.prepare(blocked)
    target = int(size * size / 700)
    trees: list[TreeTruth] = []
    placed = np.zeros((0, 3))  # x, y, crown radius of the trees so far
    for _ in range(target * 20):
        if len(trees) >= target:
            break
        x, y = rng.uniform(4.0, size - 4.0, size=2)
        r = rng.uniform(1.8, 4.0)
        if blocked.distance(shapely.Point(x, y)) < r + 1.5:
            continue
        if np.any(np.hypot(placed[:, 0] - x, placed[:, 1] - y) < r + placed[:, 2]):
            continue
        g = float(terrain.height(np.array([x]), np.array([y]))[0])
        height = rng.uniform(max(5.0, 1.6 * r), 15.0)
        crown = "cone" if rng.random() < 0.3 else "ellipsoid"
        tid = f"t{len(trees) + 1}"
        trees.append(TreeTruth(tid, float(x), float(y), g + oz, g + height + oz, float(r), crown))
        placed = np.vstack([placed, [x, y, r]])
    return trees


def _overhanging_trees(
    rng: np.random.Generator,
    buildings: list[BuildingTruth],
    terrain: Terrain,
    trees: list[TreeTruth],
    frame: LocalFrame,
    share: float = 0.35,
) -> list[TreeTruth]:
    """Trees beside a wall of ``share`` of the buildings whose crowns reach over the roof.

    The trunk stands 0.5 m or more outside the footprint; the crown (3 to 5.5 m radius)
    tops the eaves by 1 to 4 m and covers about a third of its radius of the roof's edge.
    """
    footprints = [b.footprint_local for b in buildings]
    blocked = shapely.union_all(footprints) if footprints else shapely.Polygon()
    shapely.prepare(blocked)
    placed = np.array([[t.x, t.y, t.crown_radius] for t in trees]).reshape(-1, 3)
    ox, oy, oz = frame.origin
    out = []
    for b in buildings:
        if rng.random() >= share:
            continue
        ring = b.footprint_local.exterior
        r = rng.uniform(3.0, 5.5)
        for _ in range(20):
            p = ring.interpolate(rng.uniform(0, ring.length))
            q = ring.interpolate(ring.project(p) + 0.1)
            tangent = np.array([q.x - p.x, q.y - p.y])
            if not np.any(tangent):
                continue
            normal = np.array([tangent[1], -tangent[0]]) / np.linalg.norm(tangent)  # outward for a CCW ring
            x, y = np.array([p.x, p.y]) + normal * (0.5 + 0.65 * r)
            if blocked.distance(shapely.Point(x, y)) < 0.5 or b.footprint_local.contains(shapely.Point(x, y)):
                continue
            if np.any(np.hypot(placed[:, 0] - x, placed[:, 1] - y) < 0.7 * (r + placed[:, 2])):
                continue
            g = float(terrain.height(np.array([x]), np.array([y]))[0])
            top = min(b.eave_z - oz + rng.uniform(1.0, 4.0), g + 28.0)
            tid = f"t{len(trees) + len(out) + 1}"
            out.append(TreeTruth(tid, float(x), float(y), g + oz, top + oz, float(r), "ellipsoid"))
            placed = np.vstack([placed, [x, y, r]])
            break
    return out


def _groves(
    rng: np.random.Generator,
    size: float,
    terrain: Terrain,
    footprints: list[shapely.Polygon],
    trees: list[TreeTruth],
    oz: float,
) -> list[TreeTruth]:
    """One to three groves: 5 to 10 trees whose crowns touch, on free ground.

    Each grove's crowns (2.5 to 4 m radius, 7 to 14 m high, their centres 1.3 crown
    radii apart in a sunflower pattern) make one closed canopy of about 75 to 300 m2,
    clear of the buildings by 1 m and of the trees already planted.
    """
    blocked = shapely.union_all(footprints) if footprints else shapely.Polygon()
    shapely.prepare(blocked)
    placed = np.array([[t.x, t.y, t.crown_radius] for t in trees]).reshape(-1, 3)
    out: list[TreeTruth] = []
    for _ in range(int(rng.integers(1, 4))):
        n = int(rng.integers(5, 11))
        r = rng.uniform(2.5, 4.0, n)
        k = np.arange(n)
        spread = 0.8 * r.mean() * np.sqrt(k)  # a sunflower spiral: neighbours 1.3 radii apart
        angle = k * np.pi * (3.0 - np.sqrt(5.0))
        offsets = np.column_stack([spread * np.cos(angle), spread * np.sin(angle)])
        for _ in range(40):
            centre = rng.uniform(6.0, size - 6.0, size=2)
            xy = centre + offsets
            if np.any(xy < 2.0) or np.any(xy > size - 2.0):
                continue
            crowns = shapely.union_all([shapely.Point(p).buffer(ri + 1.0) for p, ri in zip(xy, r, strict=True)])
            if crowns.intersects(blocked):
                continue
            gap = np.hypot(placed[:, None, 0] - xy[None, :, 0], placed[:, None, 1] - xy[None, :, 1])
            if np.any(gap < placed[:, None, 2] + r[None, :]):
                continue
            g = terrain.height(xy[:, 0], xy[:, 1])
            heights = rng.uniform(7.0, 14.0, n)
            for (x, y), ri, gi, hi in zip(xy, r, g, heights, strict=True):
                tid = f"t{len(trees) + len(out) + 1}"
                out.append(TreeTruth(tid, float(x), float(y), float(gi) + oz, float(gi + hi) + oz, float(ri), "ellipsoid"))
            placed = np.vstack([placed, np.column_stack([xy, r])])
            break
    return out


# --------------------------------------------------------------------------- the city


@dataclass
class SyntheticCity:
    """A procedural city and its truth.

    Attributes
    ----------
    seed : int
    size : float
        The city covers local ``[0, size] x [0, size]``; the terrain extends beyond.
    crs : str
        World CRS, "EPSG:32631".
    origin : (3,) tuple of float
        World coordinates of the local origin: ``world = local + origin``.
    terrain : Terrain
    streets : StreetGrid
    buildings : list of BuildingTruth
    trees : list of TreeTruth
    vertices : (n, 3) float64
        Local vertices of every surface (terrain, buildings, trees).
    faces : (m, 3) int64
        Triangles, oriented outward / upward.
    face_material : (m,) int8
        Index into :data:`MATERIALS` per triangle.
    face_tint : (m, 3) float32
        RGB albedo multiplier per triangle (per-building roof colour).
    face_owner : (m,) int32
        -1 for terrain, building index, or ``1000000 + tree index``.
    params : dict
        The arguments of :func:`make_city` that rebuild this city.
    """

    seed: int
    size: float
    crs: str
    origin: tuple[float, float, float]
    terrain: Terrain
    streets: StreetGrid
    buildings: list[BuildingTruth]
    trees: list[TreeTruth]
    vertices: np.ndarray
    faces: np.ndarray
    face_material: np.ndarray
    face_tint: np.ndarray
    face_owner: np.ndarray
    params: dict = field(default_factory=dict)
    _scene: object = field(default=None, repr=False, compare=False)

    @property
    def frame(self) -> LocalFrame:
        return LocalFrame(self.origin)

    def ground_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """World terrain height at world (x, y) (exact, the terrain mesh), shape of ``x``."""
        ox, oy, oz = self.origin
        return self.terrain.height(np.asarray(x) - ox, np.asarray(y) - oy) + oz

    def raycaster(self):
        """An :class:`open3d.t.geometry.RaycastingScene` of every surface (local, cached).

        The single geometry's primitive ids index ``faces`` and the ``face_*`` arrays.
        """
        if self._scene is None:
            from recon3d.core.o3d import open3d

            o3d = open3d()
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(self.vertices.astype(np.float32)),
                o3d.core.Tensor(self.faces.astype(np.uint32)),
            )
            self._scene = scene
        return self._scene

    def bounds(self) -> tuple[float, float, float, float]:
        """World (west, south, east, north) of the city area."""
        ox, oy, _ = self.origin
        return (ox, oy, ox + self.size, oy + self.size)


def make_city(
    seed: int = 0,
    *,
    size: float = 200.0,
    n_buildings: int | None = None,
    margin: float | None = None,
    origin: tuple[float, float, float] = _DEFAULT_ORIGIN,
    crs: str = "EPSG:32631",
    terrain: str = "gentle",
    layout: str = "regular",
    trees: str = "beside",
    groves: bool = False,
    superstructures: bool = False,
) -> SyntheticCity:
    """Build a procedural city, deterministic for a given seed.

    Parameters
    ----------
    seed : int
    size : float
        Side of the square city area in metres (at least one lot and its street).
    n_buildings : int, optional
        Number of buildings; default one per built lot of the layout. At most the
        number of lots.
    margin : float, optional
        How far the terrain extends beyond the city area (default ``size``, so
        oblique views of the city see terrain to the image borders).
    origin : (3,) float
        World coordinates of the local origin.
    crs : str
    terrain : {"gentle", "flat", "slope", "hilly"}
        See :data:`TERRAINS`: a few metres of relief, none, a 10 % incline, hills of
        up to 15 m.
    layout : {"regular", "dense", "sparse", "none"}
        See :data:`LAYOUTS`: 36 m lots, 25 m lots with 6 m streets, 40 % of the 36 m
        lots built, or no building.
    trees : {"none", "beside", "over"}
        No trees; trees on open ground clear of the buildings; or those plus trees
        beside a third of the buildings whose crowns reach over the roof.
    groves : bool
        Also one to three groves of 5 to 10 touching crowns (75 to 300 m2 of closed
        canopy) on open ground; ignored with ``trees="none"``.
    superstructures : bool
        Also roof parts (:attr:`BuildingTruth.parts`): stair houses and light wells
        on flat roofs, dormers on gable and shed roofs, for seven buildings in ten.

    Returns
    -------
    SyntheticCity

    Raises
    ------
    ValueError
        ``n_buildings`` exceeds the number of lots, the city is too small, or an
        unknown terrain, layout or tree placement.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"layout {layout!r} is not one of {tuple(LAYOUTS)}")
    if trees not in TREES:
        raise ValueError(f"trees {trees!r} is not one of {TREES}")
    plan = LAYOUTS[layout]
    frame = LocalFrame(tuple(float(v) for v in origin))
    ground = _make_terrain(_rng(seed, 1), size, size if margin is None else margin, terrain)
    streets = _street_grid(size, plan)
    n_lots = streets.n**2
    n = (max(1, round(plan.built * n_lots)) if plan.built > 0 else 0) if n_buildings is None else int(n_buildings)
    if n > n_lots:
        raise ValueError(
            f"{n} buildings do not fit a {size} m city ({n_lots} lots); make it larger"
        )
    rng = _rng(seed, 2)
    lots = sorted(rng.choice(n_lots, size=n, replace=False).tolist())
    kinds = _building_kinds(n, rng)
    buildings = []
    parts_rng = _rng(seed, 7) if superstructures else None
    for k, (lot, (plan_kind, roof)) in enumerate(zip(lots, kinds, strict=True)):
        poly = streets.lot(lot % streets.n, lot // streets.n)
        buildings.append(
            _make_building(f"b{k + 1}", plan_kind, roof, poly, ground, frame, rng, plan.setback, parts_rng)
        )
    footprints = [b.footprint_local for b in buildings]
    planted: list[TreeTruth] = []
    if trees != "none":
        planted = _make_trees(_rng(seed, 3), size, ground, footprints, frame.origin[2])
    if trees == "over":
        planted += _overhanging_trees(_rng(seed, 5), buildings, ground, planted, frame)
    if groves and trees != "none":
        planted += _groves(_rng(seed, 6), size, ground, footprints, planted, frame.origin[2])
    city = _assemble(seed, size, crs, frame, ground, streets, buildings, planted)
    city.params = {
        "seed": int(seed), "size": float(size), "n_buildings": n_buildings, "margin": margin,
        "origin": list(frame.origin), "crs": crs, "terrain": terrain, "layout": layout, "trees": trees,
    }
    if groves and trees != "none":
        city.params["groves"] = True
    if superstructures:
        city.params["superstructures"] = True
    log.info(
        "synthetic city seed %d: %.0f m, %s terrain, %s layout, %d buildings, %d trees, %d triangles",
        seed, size, terrain, layout, len(buildings), len(planted), len(city.faces),
    )
    return city


def _assemble(seed, size, crs, frame, terrain, streets, buildings, trees) -> SyntheticCity:
    """Merge every surface into one triangle soup with per-face attributes."""
    rng = _rng(seed, 4)
    verts, faces, mats, tints, owners = [], [], [], [], []
    count = 0

    def add(v, f, mat, tint, owner):
        nonlocal count
        verts.append(np.asarray(v, np.float64))
        faces.append(np.asarray(f, np.int64) + count)
        mats.append(np.asarray(mat, np.int8) * np.ones(len(f), np.int8))
        tints.append(np.tile(np.asarray(tint, np.float32), (len(f), 1)))
        owners.append(np.full(len(f), owner, np.int32))
        count += len(v)

    tv, tf = terrain.mesh()
    add(tv, tf, GROUND, (1.0, 1.0, 1.0), -1)
    for k, b in enumerate(buildings):
        mesh = b.solid.to_trimesh()
        sem = np.asarray(mesh.metadata["semantics"])
        roof_mat = GRAVEL if b.roof_type == "flat" else TILES
        mat = np.where(sem == "RoofSurface", roof_mat, WALL)
        tint = rng.uniform(0.75, 1.2) * rng.uniform(0.92, 1.08, 3)
        add(mesh.vertices, mesh.faces, mat, tint, k)
        for _, part, _ in b.parts:
            pm = part.to_trimesh()
            roof = np.asarray(pm.metadata["semantics"]) == "RoofSurface"
            add(pm.vertices, pm.faces, np.where(roof, roof_mat, WALL), tint, k)
    for k, t in enumerate(trees):
        tint = rng.uniform(0.8, 1.2, 3)
        for mesh, mat in _tree_meshes(t, frame.origin[2]):
            add(mesh.vertices, mesh.faces, mat, tint, 1_000_000 + k)
    return SyntheticCity(
        seed=seed,
        size=float(size),
        crs=crs,
        origin=frame.origin,
        terrain=terrain,
        streets=streets,
        buildings=buildings,
        trees=trees,
        vertices=np.concatenate(verts),
        faces=np.concatenate(faces),
        face_material=np.concatenate(mats),
        face_tint=np.concatenate(tints),
        face_owner=np.concatenate(owners),
    )


# --------------------------------------------------------------------------- truth


#: Cells of a truth grid computed at once: the grids of a large survey hold tens of
#: millions of cells, and their rays and projections several times that in bytes.
BLOCK_CELLS = 2**21


def row_blocks(shape: tuple[int, int], cells: int | None = None) -> list[slice]:
    """Consecutive row slices of a (rows, cols) grid, each of at most ``cells`` cells
    (default :data:`BLOCK_CELLS`) or one row."""
    rows, cols = shape
    step = max(1, (cells or BLOCK_CELLS) // max(cols, 1))
    return [slice(r, min(r + step, rows)) for r in range(0, rows, step)]


def cell_centres(transform: Affine, shape: tuple[int, int], rows: slice | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World x, y (rows, cols) of the cell centres of a grid (of its ``rows`` only, if given)."""
    n, cols = shape
    rows = rows or slice(0, n)
    c, r = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows.start, rows.stop) + 0.5)
    x = transform.c + c * transform.a + r * transform.b
    y = transform.f + c * transform.d + r * transform.e
    return x, y


def truth_dsm(city: SyntheticCity, transform: Affine, shape: tuple[int, int]) -> np.ndarray:
    """Highest surface at each cell centre, by vertical ray casting.

    Parameters
    ----------
    city : SyntheticCity
    transform : affine.Affine
        World grid, rasterio convention (pixel corners; centres at +0.5).
    shape : (rows, cols)

    Returns
    -------
    (rows, cols) float32
        World heights; NaN where no surface is hit (off the terrain).
    """
    from recon3d.core.o3d import open3d

    o3d = open3d()
    ox, oy, oz = city.origin
    top = city.vertices[:, 2].max() + 10.0
    out = np.empty(shape, np.float32)
    for rows in row_blocks(shape):
        x, y = cell_centres(transform, shape, rows)
        rays = np.zeros((*x.shape, 6), np.float32)
        rays[..., 0], rays[..., 1], rays[..., 2] = x - ox, y - oy, top
        rays[..., 5] = -1.0
        t = city.raycaster().cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        out[rows] = np.where(np.isfinite(t), top - t + oz, np.nan)
    return out


def truth_dtm(city: SyntheticCity, transform: Affine, shape: tuple[int, int]) -> np.ndarray:
    """Terrain height at each cell centre (the exact terrain mesh, also under buildings).

    Returns
    -------
    (rows, cols) float32
        World heights.
    """
    out = np.empty(shape, np.float32)
    for rows in row_blocks(shape):
        out[rows] = city.ground_height(*cell_centres(transform, shape, rows))
    return out


def truth_disparity(city: SyntheticCity, pair, offset) -> np.ndarray:
    """Exact left-image disparity of a rectified pair of the city, by ray casting.

    The ray through each rectified left pixel centre is cast from the left camera
    into the city; its first hit is projected into the rectified right view. This
    is what a perfect matcher would return, occlusions included (a point hidden
    from the right image still has its geometric disparity).

    Parameters
    ----------
    city : SyntheticCity
    pair : recon3d.stereo.rectify.RectifiedPair
        A rectified pair of the city's rendered scene (cameras in model coordinates).
    offset : (3,) float
        The scene's georeferencing offset: world = model + offset.

    Returns
    -------
    (H, W) float32
        Disparity in pixels (``x_right = x_left - d``); NaN where the ray hits nothing.
    """
    from recon3d.core.o3d import open3d

    o3d = open3d()
    h, w = pair.left.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    # rectified pixel -> rectified frame -> left camera frame -> model frame direction
    rays = pair.camera_left.R.T @ (pair.R1.T @ (np.linalg.inv(pair.P1[:, :3]) @ pixels))
    rays /= np.linalg.norm(rays, axis=0)
    shift = np.asarray(offset, np.float64) - np.asarray(city.origin, np.float64)  # model -> city local
    start = pair.camera_left.center + shift
    query = np.hstack([np.tile(start, (u.size, 1)), rays.T]).astype(np.float32)
    t = city.raycaster().cast_rays(o3d.core.Tensor(query))["t_hit"].numpy().astype(np.float64)
    hit = pair.camera_left.center + rays.T * t[:, None]  # model coordinates, inf where missed
    xl, xr = pair.project(np.where(np.isfinite(hit), hit, 0.0))
    d = np.where(np.isfinite(t), xl[:, 0] - xr[:, 0], np.nan)
    return d.reshape(h, w).astype(np.float32)


def checkpoints(
    city: SyntheticCity, spacing: float = 20.0
) -> tuple[np.ndarray, list[str], list[str]]:
    """Check points: ground on a grid off buildings and trees, one on top of each roof.

    Ground points lie on a ``spacing`` grid inside the city, at least 2 m from every
    footprint and 2 m beyond every tree crown; roof points are each building's
    :attr:`BuildingTruth.top`.

    Returns
    -------
    xyz : (n, 3) float64
        World coordinates.
    ids : list of str
        "g<k>" for ground, the building id with "-roof" for roofs.
    kinds : list of str
        "ground" or "roof".
    """
    half = spacing / 2
    g = np.arange(half, city.size, spacing)
    gx, gy = (a.ravel() for a in np.meshgrid(g, g))
    keep = np.ones(len(gx), bool)
    blocked = shapely.union_all([b.footprint_local for b in city.buildings])
    if not blocked.is_empty:
        keep &= shapely.distance(blocked, shapely.points(gx, gy)) >= 2.0
    for t in city.trees:
        keep &= np.hypot(gx - t.x, gy - t.y) >= t.crown_radius + 2.0
    ox, oy, oz = city.origin
    gx, gy = gx[keep], gy[keep]
    ground = np.column_stack([gx + ox, gy + oy, city.terrain.height(gx, gy) + oz])
    roofs = np.array([b.top for b in city.buildings]).reshape(-1, 3)
    xyz = np.concatenate([ground, roofs])
    ids = [f"g{k + 1}" for k in range(len(ground))] + [f"{b.id}-roof" for b in city.buildings]
    kinds = ["ground"] * len(ground) + ["roof"] * len(roofs)
    return xyz, ids, kinds


def nice_cell_size(gsd: float) -> float:
    """``gsd`` rounded to the nearest of 1, 2, 2.5 and 5 times a power of ten."""
    exp = math.floor(math.log10(gsd))
    steps = np.array([1.0, 2.0, 2.5, 5.0, 10.0]) * 10.0**exp
    return float(round(steps[np.argmin(np.abs(np.log(steps / gsd)))], 6))
