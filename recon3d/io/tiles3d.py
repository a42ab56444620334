"""3D Tiles 1.1 export of the buildings of a :class:`~recon3d.core.city.CityModel`.

A folder ``tileset.json`` + ``tiles/<level>_<x>_<y>.glb`` that CesiumJS (or any 3D
Tiles 1.1 client) streams:

- **Tiles**: a quadtree on the buildings' centres, split until a tile holds at most
  ``max_buildings`` buildings. Only the leaves hold content; the inner tiles are empty
  (``refine: ADD``) so a client loads the leaves near the camera only.
- **Content**: glTF 2.0 binary, one triangle primitive per tile (one draw call), the
  colours of :mod:`recon3d.io.gltf` (roof, wall, ground) and flat normals (CesiumJS
  renders a primitive without normals unlit).
- **Buildings as features**: ``EXT_mesh_features`` gives each vertex the feature id of
  its building and ``EXT_structural_metadata`` a property table (id, LoD, parent block,
  heights, status, reason, the building's attributes): the 3D Tiles 1.1 way, which
  CesiumJS picks (``scene.pick`` returns a ``Cesium3DTileFeature`` whose
  ``getProperty("id")`` reads the table) and styles; glTF ``extras`` are not exposed
  to picking. The node's ``extras.buildings`` lists the ids in feature-id order for
  tools without the extensions.
- **On the globe**: vertices go exactly (pyproj, per vertex) from the CRS to WGS 84
  geocentric (EPSG:4978) and then to the east-north-up frame at the centre of the
  buildings; ``root.transform`` is that ENU frame. Contents are y-up (glTF) and a
  client turns them z-up, ``(x, y, z)_tile = (x, -z, y)_glTF``, as the spec says.
  Each content's node ``translation`` is its tile's centre, so float32 positions stay
  within millimetres of any city size.
- **Heights**: the CRS heights (in metres) are used as WGS 84 ellipsoidal heights; no
  geoid model is applied (PROJ's grids are not installed), so over a terrain provider
  the buildings sit the geoid undulation low (about 43 m in the Netherlands, 50 m in
  France). ``tileset.json`` says so in ``extras.recon3d.heights``.
- **Bounds from the data**: each tile's ``box`` encloses its buildings (in the ENU
  frame); the geometric error of an inner tile is the size (3-D diagonal) of its
  largest building, the error of leaving its buildings out; leaves have 0.

The bytes depend only on the model (no time stamp, fixed order).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyproj

from recon3d.core.city import Building, CityModel
from recon3d.core.geo import crs_name, crs_units
from recon3d.errors import CRSError
from recon3d.io.cityjson import building_attributes
from recon3d.io.glb import Binary, accessor, glb
from recon3d.io.gltf import GLTF_FROM_LOCAL
from recon3d.io.obj import MATERIALS, highest_lod

log = logging.getLogger(__name__)

__all__ = ["MAX_BUILDINGS", "enu_frame", "to_ecef", "write_3dtiles"]

#: Buildings a content tile holds at most (a quadtree cell is split above it).
MAX_BUILDINGS = 32
#: Quadtree depth at which cells are no longer split, whatever they hold.
MAX_LEVEL = 16
#: Value of a numeric building property the building does not have.
NO_DATA = -9999.0



# --------------------------------------------------------------------------- public


def write_3dtiles(city: CityModel, folder: str | Path, *, max_buildings: int = MAX_BUILDINGS) -> None:
    """Write the buildings with a solid as a 3D Tiles 1.1 tileset in ``folder`` (atomic).

    The tileset is built in a private folder beside ``folder`` and swapped in at the
    end (an existing ``folder`` is replaced).

    Parameters
    ----------
    city : CityModel
        Buildings with solids in ``city.frame``; ``city.crs`` places them on the globe.
    folder : path
        Receives ``tileset.json`` and ``tiles/*.glb``.
    max_buildings : int
        Most buildings in one content tile.

    Raises
    ------
    CRSError
        When the model has no CRS.
    """
    from recon3d.pipeline.output import publish

    if city.crs is None:
        raise CRSError(f"{folder}: the buildings have no CRS; 3D Tiles need one to be placed on the globe")
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        tiles = _write_tileset(city, work, max_buildings)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(work, 0o777 & ~umask)  # mkdtemp's 0700 would hide the product
        publish(work, folder)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    log.info("wrote %d content tiles to %s", tiles, folder)


def to_ecef(xyz: np.ndarray, crs: pyproj.CRS) -> np.ndarray:
    """WGS 84 geocentric coordinates (EPSG:4978, metres) of points in a projected CRS.

    The horizontal part goes through PROJ's best available transformation to WGS 84;
    the heights, converted to metres, are taken as ellipsoidal heights.

    Parameters
    ----------
    xyz : (n, 3) float
        World coordinates in ``crs`` (its units).
    crs : pyproj.CRS
        Projected or compound (projected + vertical) CRS.

    Returns
    -------
    (n, 3) float64
    """
    lon, lat, h = _geodetic(np.asarray(xyz, dtype=np.float64).reshape(-1, 3), crs)
    x, y, z = _GEODETIC_TO_ECEF.transform(lon, lat, h)
    return np.column_stack([x, y, z])


def enu_frame(ecef: np.ndarray) -> np.ndarray:
    """(4, 4) east-north-up frame at a geocentric point: ``ecef = M @ [e, n, u, 1]``.

    Parameters
    ----------
    ecef : (3,) float
        Origin of the frame in EPSG:4978.
    """
    lon, lat, _ = _ECEF_TO_GEODETIC.transform(*ecef, radians=True)
    sl, cl, sp, cp = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
    m = np.eye(4)
    m[:3, 0] = (-sl, cl, 0.0)
    m[:3, 1] = (-sp * cl, -sp * sl, cp)
    m[:3, 2] = (cp * cl, cp * sl, sp)
    m[:3, 3] = ecef
    return m


# --------------------------------------------------------------------------- placing


_GEODETIC_TO_ECEF = pyproj.Transformer.from_crs(4979, 4978, always_xy=True)
_ECEF_TO_GEODETIC = pyproj.Transformer.from_crs(4978, 4979, always_xy=True)


def _horizontal(crs: pyproj.CRS) -> pyproj.CRS:
    return crs.sub_crs_list[0] if crs.is_compound else crs


def _to_wgs84(crs: pyproj.CRS) -> pyproj.Transformer:
    """PROJ's best available transformation from the horizontal CRS to WGS 84 lon/lat.

    Taken once, not per point, so every vertex goes through the same operation.
    """
    from pyproj.transformer import TransformerGroup

    group = TransformerGroup(_horizontal(crs), 4326, always_xy=True)
    if group.transformers:
        return group.transformers[0]
    return pyproj.Transformer.from_crs(_horizontal(crs), 4326, always_xy=True)


def _geodetic(xyz: np.ndarray, crs: pyproj.CRS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n,) longitudes, latitudes (degrees) and heights (metres) of (n, 3) CRS points."""
    lon, lat = _to_wgs84(crs).transform(xyz[:, 0], xyz[:, 1])
    lon, lat = np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)
    if not (np.isfinite(lon).all() and np.isfinite(lat).all()):
        raise CRSError(f"PROJ cannot bring coordinates of {crs_name(crs)} to WGS 84 (is the CRS right?)")
    return lon, lat, xyz[:, 2] * crs_units(crs).vertical


def _heights_note(crs: pyproj.CRS) -> str:
    """What the tileset's heights are, for ``extras.recon3d.heights``."""
    if crs.is_compound and len(crs.sub_crs_list) > 1:
        return f"{crs.sub_crs_list[1].name} ({crs_name(crs.sub_crs_list[1])}) used as WGS 84 ellipsoidal heights (no geoid model applied)"
    return "the CRS heights used as WGS 84 ellipsoidal heights (the CRS has no vertical datum)"


# --------------------------------------------------------------------------- buildings


@dataclass
class _Item:
    """One building as a tile feature: its triangle corners in the tileset's ENU frame.

    Attributes
    ----------
    corners : (3 m, 3) float64
        Corners of its m triangles, ENU metres, z up.
    rgba : (3 m, 4) uint8
        Colour of each corner.
    props : dict
        Its feature properties (JSON values).
    lo, hi : (3,) float64
        Corners of its bounding box.
    """

    corners: np.ndarray
    rgba: np.ndarray
    props: dict
    lo: np.ndarray = field(init=False)
    hi: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.lo, self.hi = self.corners.min(axis=0), self.corners.max(axis=0)

    @property
    def size(self) -> float:
        """3-D diagonal of its bounding box (metres)."""
        return float(np.linalg.norm(self.hi - self.lo))


def _world_corners(city: CityModel, building: Building, lod: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The building's world vertices (n, 3), the (3 m,) vertex of each corner of its
    triangles, and the corners' (3 m, 4) uint8 colours.

    The triangles are the solid's closed mesh (:meth:`~recon3d.core.city.Solid.mesh`),
    one corner per triangle vertex so each surface type keeps its colour (:data:`MATERIALS`).
    """
    solid = building.solids[lod]
    vertices, faces, surface = solid.mesh()
    grey = (0.7, 0.7, 0.7)
    rgb = np.array([MATERIALS.get(k, (None, grey))[1] for k in solid.semantics] or [grey])[surface]
    rgba = np.column_stack([np.rint(rgb * 255), np.full(len(rgb), 255)]).astype(np.uint8)
    world = city.frame.to_world(np.asarray(vertices, dtype=np.float64))
    return world, np.asarray(faces, dtype=np.int64).reshape(-1), np.repeat(rgba, 3, axis=0)


def _properties(building: Building, lod: str) -> dict:
    """The feature properties of a building: id, LoD, parent block, then its attributes."""
    props = {"id": str(building.id), "lod": lod}
    if building.parent is not None:
        props["parent"] = str(building.parent)
    return {**props, **building_attributes(building)}


def _items(city: CityModel) -> tuple[list[_Item], np.ndarray]:
    """The buildings with a solid, in the ENU frame at their centre, and that (4, 4) frame."""
    picked, parts = [], []
    for b in city.buildings:
        lod = highest_lod(b)
        part = _world_corners(city, b, lod) if lod is not None else None
        if part is not None and len(part[1]):  # a solid without triangles shows nothing
            picked.append((b, lod))
            parts.append(part)
    # each vertex is brought to the globe once (PROJ is the cost), then handed to its corners
    starts = np.cumsum([0] + [len(w) for w, _, _ in parts])[:-1]
    corners = np.concatenate([index + start for (_, index, _), start in zip(parts, starts, strict=True)]) if parts else None
    vertices = np.concatenate([w for w, _, _ in parts]) if parts else _fallback_points(city)
    world = vertices[corners] if parts else vertices
    lo, hi = world.min(axis=0), world.max(axis=0)
    centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    frame = enu_frame(to_ecef(centre[None], city.crs)[0])
    if not parts:
        return [], frame
    enu = (to_ecef(vertices, city.crs)[corners] - frame[:3, 3]) @ frame[:3, :3]  # rows: M.T @ (p - t)
    splits = np.cumsum([len(index) for _, index, _ in parts])[:-1]
    items = [
        _Item(corners_enu, rgba, _properties(b, lod))
        for corners_enu, (_, _, rgba), (b, lod) in zip(np.split(enu, splits), parts, picked, strict=True)
    ]
    return items, frame


def _fallback_points(city: CityModel) -> np.ndarray:
    """(n, 3) world points placing a tileset without any solid: footprints, else the origin."""
    pts = []
    for b in city.buildings:
        if b.footprint is None or b.footprint.is_empty:
            continue
        xy = np.asarray(b.footprint.exterior.coords)[:, :2]
        pts.append(np.column_stack([xy, np.full(len(xy), 0.0 if math.isnan(b.ground_z) else b.ground_z)]))
    return np.concatenate(pts) if pts else np.asarray(city.frame.origin, dtype=np.float64)[None]


# --------------------------------------------------------------------------- quadtree


@dataclass
class _Cell:
    """A quadtree cell: its address and the buildings (indices) whose centre falls in it."""

    level: int
    x: int
    y: int
    members: list[int]
    children: list[_Cell] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"{self.level}_{self.x}_{self.y}"


def _quadtree(centres: np.ndarray, max_buildings: int) -> _Cell:
    """Split the square around (n, 2) centres until a cell holds at most ``max_buildings``."""
    lo = centres.min(axis=0) if len(centres) else np.zeros(2)
    size = float(np.ptp(centres, axis=0).max()) if len(centres) else 0.0
    unit = (centres - lo) / size if size > 0 else np.zeros_like(centres)
    root = _Cell(0, 0, 0, list(range(len(centres))))
    _split(root, unit, max_buildings)
    return root


def _split(cell: _Cell, unit: np.ndarray, max_buildings: int) -> None:
    """Split ``cell`` (in place, recursively) by the (n, 2) centres in the unit square."""
    if len(cell.members) <= max_buildings or cell.level >= MAX_LEVEL or not np.ptp(unit[cell.members], axis=0).any():
        return  # small enough, deep enough, or all its centres at one point
    n = 2 ** (cell.level + 1)
    index = np.clip(np.floor(unit[cell.members] * n).astype(np.int64), 0, n - 1)
    groups: dict[tuple[int, int], list[int]] = {}
    for member, (ix, iy) in zip(cell.members, index.tolist(), strict=True):
        groups.setdefault((iy, ix), []).append(member)
    for iy, ix in sorted(groups):
        child = _Cell(cell.level + 1, ix, iy, groups[(iy, ix)])
        _split(child, unit, max_buildings)
        cell.children.append(child)
    cell.members = []


def _leaves(cell: _Cell) -> list[_Cell]:
    """The cells under ``cell`` (itself included) that hold buildings, in tree order."""
    return [cell] if not cell.children else [leaf for c in cell.children for leaf in _leaves(c)]


def _subtree(cell: _Cell) -> list[int]:
    """Indices of the buildings under ``cell``."""
    return [m for leaf in _leaves(cell) for m in leaf.members]


# --------------------------------------------------------------------------- tileset JSON


def _box(lo: np.ndarray, hi: np.ndarray) -> list[float]:
    """12-number ``box`` (centre, three half axes) enclosing the (3,) corners ``lo``, ``hi``.

    Millimetres, rounded outward: the box always encloses the points.
    """
    centre = np.round(0.5 * (lo + hi), 3)
    half = np.round(np.maximum(0.5 * (hi - lo), 0.005) + 0.001, 3)
    return [float(v) for v in (*centre, half[0], 0, 0, 0, half[1], 0, 0, 0, half[2])]


def _ceil_mm(value: float) -> float:
    """``value`` rounded up to the millimetre (a geometric error never understated)."""
    return math.ceil(value * 1000.0) / 1000.0


def _tile_json(cell: _Cell, items: list[_Item]) -> dict:
    """The tile object of ``cell`` and its children (content uri for a leaf)."""
    members = _subtree(cell)
    lo = np.min([items[m].lo for m in members], axis=0)
    hi = np.max([items[m].hi for m in members], axis=0)
    tile = {"boundingVolume": {"box": _box(lo, hi)}}
    if cell.children:
        tile["geometricError"] = _ceil_mm(max(items[m].size for m in members))
        tile["children"] = [_tile_json(c, items) for c in cell.children]
    else:
        tile["geometricError"] = 0.0
        tile["content"] = {"uri": f"tiles/{cell.name}.glb"}
    return tile


def _tileset_json(root: _Cell, items: list[_Item], frame: np.ndarray, city: CityModel, max_buildings: int) -> dict:
    """The tileset object: the tiles, the (4, 4) ENU ``frame`` as the root's transform.

    The tileset's own geometric error (the error of showing nothing) is the diagonal of
    the root's box.
    """
    if items:
        tile = _tile_json(root, items)
    else:  # nothing to show: an empty root of 1 m at the centre
        tile = {"boundingVolume": {"box": [0.0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]}, "geometricError": 0.0}
    head = {k: tile.pop(k) for k in ("boundingVolume", "geometricError")}
    tile = {**head, "refine": "ADD", "transform": [float(v) for v in frame.T.reshape(-1)], **tile}  # column-major
    half = np.asarray(tile["boundingVolume"]["box"][3:]).reshape(3, 3)
    lon, lat, h = _ECEF_TO_GEODETIC.transform(*frame[:3, 3])
    return {
        "asset": {"version": "1.1"},
        "geometricError": _ceil_mm(2.0 * float(np.linalg.norm(half.sum(axis=0)))),
        "root": tile,
        "extras": {"recon3d": {
            "crs": crs_name(city.crs),
            "centre": {"lon": round(lon, 9), "lat": round(lat, 9), "height": round(h, 3)},
            "crs_to_wgs84": _to_wgs84(city.crs).description,
            "heights": _heights_note(city.crs),
            "buildings": len(items),
            "max_buildings_per_tile": max_buildings,
            "feature_properties": "EXT_structural_metadata property table 'buildings' in each content",
        }},
    }


# --------------------------------------------------------------------------- writing


def _write_tileset(city: CityModel, folder: Path, max_buildings: int) -> int:
    """Write ``tileset.json`` and the content tiles into ``folder``; the number of contents."""
    items, frame = _items(city)
    if not items:
        log.warning("no building has a solid: %s holds an empty tileset", folder)
    centres = np.array([0.5 * (i.lo + i.hi)[:2] for i in items]).reshape(-1, 2)
    root = _quadtree(centres, max(1, int(max_buildings)))
    schema = _schema(items)
    leaves = _leaves(root) if items else []
    (folder / "tiles").mkdir()
    for leaf in leaves:
        glb = _content_glb([items[m] for m in leaf.members], schema, leaf.name)
        (folder / "tiles" / f"{leaf.name}.glb").write_bytes(glb)
    doc = _tileset_json(root, items, frame, city, max_buildings)
    (folder / "tileset.json").write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return len(leaves)


# --------------------------------------------------------------------------- metadata


@dataclass(frozen=True)
class _Property:
    """A building property of the metadata schema: its key and its type."""

    key: str  # the attribute's name
    ident: str  # the schema's property id (letters, digits, underscores)
    kind: str  # "STRING", "FLOAT64" or "BOOLEAN"
    missing: bool  # some building lacks it


def _identifier(key: str, taken: set[str]) -> str:
    ident = "".join(c if (c.isascii() and c.isalnum()) or c == "_" else "_" for c in key) or "_"
    if ident[0].isdigit():
        ident = "_" + ident
    base, n = ident, 1
    while ident in taken:
        n += 1
        ident = f"{base}_{n}"
    taken.add(ident)
    return ident


def _kind(values: list) -> str:
    if all(isinstance(v, bool) for v in values):
        return "BOOLEAN"
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return "FLOAT64"
    return "STRING"


def _schema(items: list[_Item]) -> list[_Property]:
    """The properties of every building, in order of first appearance, typed over the model."""
    keys: dict[str, None] = {}
    for item in items:
        keys.update(dict.fromkeys(item.props))
    taken: set[str] = set()
    out = []
    for key in keys:
        values = [i.props[key] for i in items if key in i.props]
        kind, missing = _kind(values), len(values) < len(items)
        if kind == "BOOLEAN" and missing:
            kind = "STRING"  # a boolean property has no "no data" value
        out.append(_Property(key, _identifier(key, taken), kind, missing))
    return out


def _class_json(schema: list[_Property]) -> dict:
    props = {}
    for p in schema:
        d = {"name": p.key, "type": p.kind} if p.kind != "FLOAT64" else {"name": p.key, "type": "SCALAR",
                                                                          "componentType": "FLOAT64"}
        if p.missing:
            d["noData"] = NO_DATA if p.kind == "FLOAT64" else ""
        else:
            d["required"] = True
        props[p.ident] = d
    return {"name": "Building", "description": "A building reconstructed by recon3d", "properties": props}


def _text(value) -> str:
    return value if isinstance(value, str) else json.dumps(value, sort_keys=True, ensure_ascii=False)


def _column(prop: _Property, items: list[_Item]) -> list[bytes]:
    """The binary buffers of one property over the tile's buildings (values[, string offsets])."""
    values = [i.props.get(prop.key) for i in items]
    if prop.kind == "FLOAT64":
        return [np.array([NO_DATA if v is None else v for v in values], dtype="<f8").tobytes()]
    if prop.kind == "BOOLEAN":
        return [np.packbits(np.array(values, dtype=bool), bitorder="little").tobytes()]
    encoded = [b"" if v is None else _text(v).encode("utf-8") for v in values]
    offsets = np.concatenate([[0], np.cumsum([len(e) for e in encoded])]).astype("<u4")
    return [b"".join(encoded), offsets.tobytes()]


# --------------------------------------------------------------------------- glTF


def _flat_normals(corners: np.ndarray) -> np.ndarray:
    """(3 m, 3) float32 unit normal of each corner's triangle (z up, (3 m, 3) corners)."""
    tri = corners.reshape(-1, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.repeat(n, 3, axis=0)


def _proper_triangles(corners: np.ndarray) -> np.ndarray:
    """(3 m,) bool: corners of triangles with an area (a normal), which are the ones kept."""
    tri = corners.reshape(-1, 3, 3)
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return np.repeat(area2 > 1e-12, 3)


def _geometry(items: list[_Item], centre: np.ndarray) -> tuple[np.ndarray, ...]:
    """Positions (relative to ``centre``), normals, colours and feature ids, glTF y-up.

    Returns
    -------
    positions, normals : (v, 3) float32
    rgba : (v, 4) uint8
    feature : (v,) float32
        Index of each vertex's building in ``items``.
    """
    corners = np.concatenate([i.corners for i in items])
    rgba = np.concatenate([i.rgba for i in items])
    feature = np.repeat(np.arange(len(items), dtype=np.float32), [len(i.corners) for i in items])
    keep = _proper_triangles(corners)
    corners, rgba, feature = corners[keep], rgba[keep], feature[keep]
    positions = ((corners - centre) @ GLTF_FROM_LOCAL.T).astype(np.float32)
    normals = (_flat_normals(corners) @ GLTF_FROM_LOCAL.T).astype(np.float32)
    return positions, normals, rgba, feature


def _metadata(items: list[_Item], schema: list[_Property], binary: Binary) -> dict:
    """The ``EXT_structural_metadata`` object: the class and the tile's property table."""
    columns = {}
    for prop in schema:
        if all(prop.key not in i.props for i in items):
            continue  # a table may leave out a property that is not required
        buffers = _column(prop, items)
        column = {"values": binary.view(buffers[0])}
        if len(buffers) > 1:
            column["stringOffsets"] = binary.view(buffers[1])
        columns[prop.ident] = column
    return {
        "schema": {"id": "recon3d_buildings", "classes": {"building": _class_json(schema)}},
        "propertyTables": [{"name": "buildings", "class": "building", "count": len(items), "properties": columns}],
    }


def _content_glb(items: list[_Item], schema: list[_Property], name: str) -> bytes:
    """GLB of one tile: its buildings as one primitive with feature ids and a property table."""
    lo, hi = np.min([i.lo for i in items], axis=0), np.max([i.hi for i in items], axis=0)
    centre = np.round(0.5 * (lo + hi), 3)
    positions, normals, rgba, feature = _geometry(items, centre)
    binary = Binary()
    accessors = [
        accessor(positions, binary, "VEC3", bounds=True),
        accessor(normals, binary, "VEC3"),
        accessor(rgba, binary, "VEC4", normalized=True),
        accessor(feature, binary, "SCALAR"),
    ]
    metadata = _metadata(items, schema, binary)
    features = {"featureIds": [{"featureCount": len(items), "attribute": 0, "propertyTable": 0}]}
    primitive = {
        "attributes": {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2, "_FEATURE_ID_0": 3},
        "material": 0, "mode": 4, "extensions": {"EXT_mesh_features": features},
    }
    node = {"name": f"tile {name}", "mesh": 0, "translation": [float(v) for v in centre @ GLTF_FROM_LOCAL.T],
            "extras": {"buildings": [i.props["id"] for i in items]}}
    data = binary.padded()
    doc = {
        "asset": {"version": "2.0", "generator": "recon3d"},
        "extensionsUsed": ["EXT_mesh_features", "EXT_structural_metadata"],
        "extensions": {"EXT_structural_metadata": metadata},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node],
        "meshes": [{"name": f"buildings {name}", "primitives": [primitive]}],
        "materials": [{"name": "building", "pbrMetallicRoughness": {
            "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "accessors": accessors,
        "bufferViews": binary.views,
        "buffers": [{"byteLength": len(data)}],
    }
    return glb(doc, data)
