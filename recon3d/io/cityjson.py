"""CityJSON 2.0 writer for the buildings of a :class:`~recon3d.core.city.CityModel`.

The file follows the CityJSON 2.0 specification (https://www.cityjson.org/specs/2.0.1/)
and validates against the 2.0.2 JSON schema:

- vertices are integers under ``transform``: ``world = vertex * scale + translate``,
  with ``translate`` the model's :class:`~recon3d.core.geo.LocalFrame` origin and
  ``scale`` a power of ten of at most 1 mm (0.001 for metric CRSs); vertices are
  deduplicated over the whole file after quantisation;
- ``lod`` is a string ("1", "2.2"); each LoD is one ``Solid`` whose single shell is
  oriented outward, with GroundSurface / WallSurface / RoofSurface semantics;
- ``metadata`` holds only the six properties CityJSON 2.0 defines (since 1.1 no
  other property is allowed there): ``referenceSystem`` as an OGC CRS URL, the
  ``geographicalExtent`` in world coordinates, ``referenceDate`` (the city model's
  ``metadata["referenceDate"]``, which the pipeline takes from the input data, else
  today), ``title`` and, when given, ``identifier`` and ``pointOfContact``;
- a building that could not be built is still written, with ``"geometry": []`` and
  its ``status`` / ``reason`` attributes, so a user sees every footprint;
- the parts of a block that detection split at height jumps (buildings sharing a
  :attr:`~recon3d.core.city.Building.parent`) are ``BuildingPart`` objects (their own
  solids and attributes, ``"parents": [block id]``) under one parent ``Building``
  without geometry (``"children"``, attributes of the whole block:
  :func:`block_attributes`). In CityJSONSeq a block and its parts share one feature.

:func:`read_cityjson` reads such a file back part by part (see there), so a
write -> read round trip gives the same buildings with the same ``parent``.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pyproj

from recon3d.core.city import Building, CityModel, Solid
from recon3d.core.dates import today
from recon3d.core.geo import LocalFrame, crs_authority, crs_name, crs_units
from recon3d.core.mesh import welded_rings
from recon3d.errors import CRSError
from recon3d.io import atomic_path

log = logging.getLogger(__name__)

__all__ = [
    "block_attributes",
    "building_attributes",
    "cityjson_dict",
    "crs_url",
    "quantisation_scale",
    "read_cityjson",
    "write_cityjson",
    "write_cityjsonseq",
]

#: Metadata properties CityJSON 2.0 defines; no other key is allowed in "metadata".
METADATA_KEYS = (
    "identifier",
    "pointOfContact",
    "referenceDate",
    "referenceSystem",
    "title",
    "geographicalExtent",
)
#: Keys of ``metadata=`` the caller may set; the other two are computed from the model.
_USER_METADATA_KEYS = ("identifier", "pointOfContact", "referenceDate", "title")
#: Authorities with an OGC CRS URL (https://www.opengis.net/def/crs/{authority}/0/{code}).
_OGC_AUTHORITIES = ("EPSG", "OGC")
#: Largest allowed quantisation step, in metres.
_MAX_STEP_M = 0.001

_OMIT = object()


def write_cityjson(city: CityModel, path: str | Path, *, metadata: dict | None = None) -> None:
    """Write ``city`` as a CityJSON 2.0 file (UTF-8, atomic).

    Parameters
    ----------
    city : CityModel
        Buildings with solids in ``city.frame`` local coordinates.
    path : str or Path
        Output file, conventionally ``*.city.json``.
    metadata : dict, optional
        ``title``, ``identifier``, ``referenceDate`` and ``pointOfContact`` (which the
        schema accepts only with ``contactName`` and ``emailAddress``). Other keys
        are not allowed in CityJSON metadata and are dropped with a warning.
    """
    doc = cityjson_dict(city, metadata)
    text = json.dumps(doc, ensure_ascii=False, separators=(",", ":"), allow_nan=False)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    n_obj, n_vert = len(doc["CityObjects"]), len(doc["vertices"])
    log.info("wrote %d buildings, %d vertices to %s", n_obj, n_vert, path)


def cityjson_dict(city: CityModel, metadata: dict | None = None) -> dict:
    """The CityJSON 2.0 document :func:`write_cityjson` serialises.

    Returns
    -------
    dict
        JSON-ready (plain Python types, no NaN).

    Raises
    ------
    ValueError
        Two buildings, or a building and a block, share an id (one would silently
        replace the other).
    """
    blocks = city.blocks()
    ids = [b.id for b in city.buildings] + list(blocks)
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise ValueError(f"duplicate building ids cannot be written to CityJSON: {dup[:5]}")
    origin = np.asarray(city.frame.origin, dtype=np.float64)
    scale = quantisation_scale(city.crs)
    solids = [(b, lod, s) for b in city.buildings for lod, s in _sorted_solids(b)]
    vertices, remaps = _quantise([s.vertices for _, _, s in solids], scale)
    geometry: dict[str, list] = {b.id: [] for b in city.buildings}
    degenerate = 0
    for (b, lod, solid), remap in zip(solids, remaps, strict=True):
        geom = _solid_geometry(solid, lod, remap)
        written = 0 if geom is None else len(geom["boundaries"][0] if solid.kind == "Solid" else geom["boundaries"])
        degenerate += len(solid.surfaces) - written
        if geom is None:
            log.warning("building %s: LoD %s %s has no valid surface, not written", b.id, lod, solid.kind)
        else:
            geometry[b.id].append(geom)
    if degenerate:
        log.warning("CityJSON: %d surfaces with fewer than 3 distinct vertices at %g CRS units were left out",
                    degenerate, float(scale[0]))
    objects: dict[str, dict] = {}
    for b in city.buildings:
        obj = {"type": "Building", "attributes": building_attributes(b), "geometry": geometry[b.id]}
        if b.parent is not None:
            if b.parent not in objects:  # the block just before its first part
                parts = blocks[b.parent]
                objects[b.parent] = {
                    "type": "Building",
                    "attributes": block_attributes(parts),
                    "children": [p.id for p in parts],
                    "geometry": [],
                }
            obj = dict(obj, type="BuildingPart", parents=[b.parent])
        objects[b.id] = obj
    return {
        "type": "CityJSON",
        "version": "2.0",
        "transform": {"scale": scale.tolist(), "translate": origin.tolist()},
        "metadata": _metadata(city, vertices, scale, origin, metadata),
        "CityObjects": objects,
        "vertices": vertices.tolist(),
    }


def quantisation_scale(crs: pyproj.CRS | None) -> np.ndarray:
    """(3,) CityJSON ``transform.scale``: powers of ten of at most 1 mm per axis.

    0.001 for metric CRSs and when the CRS is unknown; 0.001 ft (0.3 mm) for feet.
    A geographic CRS (degrees) gets 1e-9 deg horizontally (0.1 mm on the equator).
    """
    if crs is None:
        return np.full(3, _MAX_STEP_M)
    try:
        units = crs_units(crs, source="CityJSON export")
    except CRSError:
        log.warning("CityJSON: %s is not projected; quantising lon/lat to 1e-9 deg", crs_name(crs))
        return np.array([1e-9, 1e-9, _MAX_STEP_M])
    return np.array([_pow10_step(units.horizontal)] * 2 + [_pow10_step(units.vertical)])


def _pow10_step(metres_per_unit: float) -> float:
    """Largest power of ten, in CRS units, not longer than 1 mm."""
    exponent = math.floor(math.log10(_MAX_STEP_M / metres_per_unit) + 1e-9)
    return float(f"1e{exponent}")


def _sorted_solids(building: Building) -> list[tuple[str, Solid]]:
    """The building's (lod, solid) pairs, lowest LoD first."""
    return sorted(building.solids.items(), key=lambda item: float(item[0]))


def _quantise(
    vertex_sets: list[np.ndarray], scale: np.ndarray
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Quantise and deduplicate the vertices of several solids.

    Parameters
    ----------
    vertex_sets : list of (n_i, 3) float arrays
        Local-frame vertices, one array per solid.
    scale : (3,) float

    Returns
    -------
    vertices : (m, 3) int64
        Unique quantised vertices in order of first use.
    remaps : list of (n_i,) int64
        For each solid, the row in ``vertices`` of each of its vertices.
    """
    if not vertex_sets:
        return np.zeros((0, 3), np.int64), []
    q = np.rint(np.concatenate(vertex_sets) / scale).astype(np.int64)
    uniq, first, inverse = _unique_rows(q)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[inverse.reshape(-1)]
    ends = np.cumsum([len(v) for v in vertex_sets])[:-1]
    return uniq[order], np.split(index, ends)


def _unique_rows(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(q, axis=0, return_index=True, return_inverse=True)`` of (n, 3) int64
    rows, the same arrays, through one int64 key per row where the rows' span allows:
    ``axis=0`` sorts rows as structured records, several times slower on a city."""
    lo = q.min(axis=0)
    span = q.max(axis=0) - lo + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0**62:
        return np.unique(q, axis=0, return_index=True, return_inverse=True)
    key = ((q[:, 0] - lo[0]) * span[1] + (q[:, 1] - lo[1])) * span[2] + (q[:, 2] - lo[2])  # row order kept
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return q[first], first, inverse


def _solid_geometry(solid: Solid, lod: str, remap: np.ndarray) -> dict | None:
    """One CityJSON ``Solid`` (or, for surfaces read as such, ``MultiSurface``) geometry
    object, or None when no surface survives.

    Rings are re-indexed into the file's vertex list; vertices that quantisation
    merged are removed from rings (consecutive repeats), and rings left with fewer
    than 3 vertices are dropped (a surface whose outer ring goes is dropped).
    """
    surfaces, kinds = [], []
    for rings, kind in zip(welded_rings(remap, solid.surfaces), solid.semantics, strict=True):
        if rings:
            surfaces.append([r.tolist() for r in rings])
            kinds.append(kind)
    if not surfaces:
        return None
    types = list(dict.fromkeys(kinds))
    values = [types.index(k) for k in kinds]
    closed = solid.kind == "Solid"
    return {
        "type": solid.kind,
        "lod": str(lod),
        "boundaries": [surfaces] if closed else surfaces,
        "semantics": {"surfaces": [{"type": t} for t in types], "values": [values] if closed else values},
    }


def building_attributes(building: Building) -> dict[str, Any]:
    """JSON-safe attributes of a building (for CityJSON, glTF extras, reports).

    ``building.attributes`` first, then ``ground_z``, ``roof_z``, ``height``,
    ``status`` and ``reason``, which take precedence on a name clash. None and NaN
    values are omitted.
    """
    own = {
        "ground_z": building.ground_z,
        "roof_z": building.roof_z,
        "height": building.height,
        "status": building.status,
        "reason": building.reason,
    }
    clash = sorted(set(own) & set(building.attributes))
    if clash:
        log.debug("building %s: attributes %s replaced by recon3d's own", building.id, clash)
    merged = {**building.attributes, **own}
    out = {}
    for key, value in merged.items():
        safe = _json_safe(value)
        if safe is not _OMIT and safe is not None:
            out[str(key)] = safe
    return out


#: Geometry types read as surfaces that are not known to close a volume.
SURFACE_TYPES = ("MultiSurface", "CompositeSurface")

#: Attributes of a block (the parent Building of BuildingParts) that describe the whole
#: block, not a part: the reader does not pass them on to the parts.
BLOCK_KEYS = ("ground_z", "roof_z", "height", "status", "reason", "parts", "area")


def block_attributes(parts: list[Building]) -> dict[str, Any]:
    """JSON-safe attributes of the block made of ``parts`` (its parent Building).

    ``parts`` (their number), ``ground_z`` (lowest), ``roof_z`` (highest), ``height``,
    ``area`` (sum of the footprints), ``status`` ("ok" when every part is, "failed"
    when none got a solid, else "partial"), and every text attribute on which all
    parts agree (``source``...). NaN values are omitted.
    """
    ground = [b.ground_z for b in parts if math.isfinite(b.ground_z)]
    roof = [b.roof_z for b in parts if math.isfinite(b.roof_z)]
    if all(b.status == "ok" for b in parts):
        status = "ok"
    elif not any(b.solids for b in parts):
        status = "failed"
    else:
        status = "partial"
    common = {}
    first = parts[0].attributes if parts else {}
    for key, value in first.items():
        if key in BLOCK_KEYS or not isinstance(value, str):
            continue
        if all(b.attributes.get(key) == value for b in parts):
            common[key] = value
    own = {
        "parts": len(parts),
        "ground_z": min(ground) if ground else None,
        "roof_z": max(roof) if roof else None,
        "height": max(roof) - min(ground) if ground and roof else None,
        "area": round(float(sum(b.footprint.area for b in parts)), 3),
        "status": status,
    }
    out = {}
    for key, value in {**common, **own}.items():
        safe = _json_safe(value)
        if safe is not _OMIT and safe is not None:
            out[str(key)] = safe
    return out


def _json_safe(value: Any) -> Any:
    """``value`` as plain JSON types; NaN/inf are omitted (top level) or null (nested).

    numpy scalars and arrays become Python numbers and lists, dates ISO strings,
    anything else unknown its ``str()``. Returns a private sentinel for values that
    should be omitted at the top level (NaN, inf).
    """
    if isinstance(value, np.generic):
        value = value.item()
    elif isinstance(value, np.ndarray):
        value = value.tolist()
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else _OMIT
    if isinstance(value, dict):
        return {str(k): _nested(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_nested(v) for v in value]
    if isinstance(value, (_dt.date, _dt.datetime)):
        return value.isoformat()
    return str(value)


def _nested(value: Any) -> Any:
    safe = _json_safe(value)
    return None if safe is _OMIT else safe


def _metadata(
    city: CityModel,
    vertices: np.ndarray,
    scale: np.ndarray,
    origin: np.ndarray,
    extra: dict | None,
) -> dict[str, Any]:
    """The CityJSON ``metadata`` object (only the six properties the spec allows)."""
    meta: dict[str, Any] = {
        "title": "recon3d buildings",
        "referenceDate": city.metadata.get("referenceDate") or today(),
    }
    meta.update(_user_metadata(extra or {}))
    url = crs_url(city.crs)
    if url:
        meta["referenceSystem"] = url
    if len(vertices):
        world = vertices * scale + origin
        lo, hi = world.min(axis=0), world.max(axis=0)
        meta["geographicalExtent"] = [float(round(v, 6)) for v in (*lo, *hi)]
    return meta


def _user_metadata(extra: dict) -> dict[str, Any]:
    """The keys of ``extra`` CityJSON 2.0 metadata accepts; the rest is logged and dropped."""
    kept = {}
    for key, value in extra.items():
        if key not in _USER_METADATA_KEYS:
            why = (
                "computed from the model"
                if key in METADATA_KEYS
                else "not a CityJSON 2.0 metadata property"
            )
            log.warning("CityJSON metadata %r dropped (%s)", key, why)
            continue
        if key == "pointOfContact" and not (
            isinstance(value, dict) and {"contactName", "emailAddress"} <= set(value)
        ):
            log.warning(
                "CityJSON metadata pointOfContact dropped: needs contactName and emailAddress"
            )
            continue
        safe = _json_safe(value)
        if safe is not _OMIT and safe is not None:
            kept[key] = safe
    return kept


def crs_url(crs: pyproj.CRS | None) -> str | None:
    """OGC CRS URL of ``crs`` ("https://www.opengis.net/def/crs/EPSG/0/7415"), or None.

    Compound CRSs keep their compound code (EPSG:7415 = RD New + NAP height), so the
    height reference travels with the file. A compound CRS without a code of its own
    (EPSG:2994+6360) gives its horizontal part's URL: CityJSON 2.0 has one
    ``referenceSystem`` URL, and its schema takes no ``crs-compound`` URL.
    """
    if crs is None:
        return None
    auth = crs_authority(crs)
    if not auth and crs.is_compound:
        auth = crs_authority(crs.sub_crs_list[0])
        if auth:
            log.info("CityJSON: %s has no code of its own; referenceSystem names its horizontal part", crs.name)
    if not auth or auth[0].upper() not in _OGC_AUTHORITIES:
        log.warning("CityJSON: CRS %s has no EPSG/OGC code; referenceSystem omitted", crs_name(crs))
        return None
    return f"https://www.opengis.net/def/crs/{auth[0].upper()}/0/{auth[1]}"


# --------------------------------------------------------------------------- CityJSONSeq


def write_cityjsonseq(city: CityModel, path: str | Path, *, metadata: dict | None = None) -> None:
    """Write ``city`` as CityJSON Text Sequences (``.city.jsonl``): a header line, then one
    ``CityJSONFeature`` per building with its own vertex list, so large models stream.

    A block (parent ``Building``) and its ``BuildingPart`` children travel in one
    feature, whose ``id`` is the block's; features follow the order of the model's
    buildings (a block where its first part is).
    """
    doc = cityjson_dict(city, metadata)
    header = {k: doc[k] for k in ("type", "version", "transform", "metadata")}
    header.update(CityObjects={}, vertices=[])
    vertices = np.asarray(doc["vertices"], dtype=np.int64).reshape(-1, 3)
    lines = [json.dumps(header, ensure_ascii=False, separators=(",", ":"))]
    objects = doc["CityObjects"]
    for bid, top in objects.items():
        if "parents" in top:
            continue  # written with its parent
        members = {bid: top, **{c: objects[c] for c in top.get("children", [])}}
        geoms = [g for obj in members.values() for g in obj["geometry"]]
        used = sorted({i for g in geoms for i in _flatten_indices(g["boundaries"])})
        remap = {old: new for new, old in enumerate(used)}
        members = {
            oid: dict(obj, geometry=[_reindexed(g, remap) for g in obj["geometry"]])
            for oid, obj in members.items()
        }
        feature = {
            "type": "CityJSONFeature",
            "id": bid,
            "CityObjects": members,
            "vertices": vertices[used].tolist(),
        }
        lines.append(json.dumps(feature, ensure_ascii=False, separators=(",", ":")))
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _reindexed(geometry: dict, remap: dict[int, int]) -> dict:
    return dict(geometry, boundaries=_reindex(geometry["boundaries"], remap))


def _flatten_indices(nested) -> list[int]:
    if isinstance(nested, int):
        return [nested]
    return [i for item in nested for i in _flatten_indices(item)]


def _reindex(nested, remap: dict[int, int]):
    if isinstance(nested, int):
        return remap[nested]
    return [_reindex(item, remap) for item in nested]


# --------------------------------------------------------------------------- reader


def read_cityjson(
    path: str | Path, *, crs: pyproj.CRS | None = None, parts: bool | None = None
) -> CityModel:
    """Read a CityJSON 1.1 / 2.0 file or a CityJSONSeq (``.jsonl``) into a :class:`CityModel`.

    Every ``Building`` becomes one :class:`Building` (its ``BuildingPart`` children
    included): solids by LoD (``Solid`` geometries; the first shell, the first part's
    solid when several parts have one of that LoD; a LoD given only as
    ``MultiSurface`` or ``CompositeSurface`` is read as a :class:`Solid` of that
    ``kind``), a footprint (union of the plan
    views of its ground surfaces, or of all surfaces when there are no semantics;
    the largest polygon), and its attributes. ``ground_z``/``roof_z`` are taken from
    the attributes recon3d writes, else from the geometry.

    A block recon3d wrote (a ``Building`` whose ``parts`` attribute is the number of
    its ``BuildingPart`` children) is read instead as its parts, in file order: one
    :class:`Building` per part, with the part's id, solids and attributes, the block's
    attributes it does not have itself (except the block-wide :data:`BLOCK_KEYS`),
    and ``parent`` set to the block's id; the block's own geometry, if any, is not
    read. Geometries not read (MultiSolids, a second geometry of a LoD, objects that
    are no building) are counted by type and reason in the model's
    ``metadata["skipped_geometries"]``. So what :func:`write_cityjson` wrote comes
    back as the same buildings in the same order (a CityJSONSeq file: grouped by block); a part without geometry
    (a failed one) is not read, as a stand-alone building without geometry is not.

    Parameters
    ----------
    path : str or Path
    crs : pyproj.CRS, optional
        Replaces the file's ``referenceSystem``.
    parts : bool, optional
        True: every Building with two or more BuildingParts is read as its parts;
        False: parts are always folded into their Building; None (default): only
        recon3d's blocks are read as parts.

    Raises
    ------
    InputError
        Not CityJSON, an unsupported version, or no building.
    """
    from recon3d.errors import InputError
    from recon3d.io import require_file

    path = require_file(path, "CityJSON")
    docs = _read_documents(path)
    if not docs or not all(isinstance(d, dict) for d in docs):
        raise InputError(f"{path}: not CityJSON (the top level is not a JSON object)")
    head = docs[0]
    if head.get("type") != "CityJSON" or str(head.get("version")) not in ("1.1", "2.0"):
        raise InputError(f"{path}: not CityJSON 1.1 or 2.0 (type {head.get('type')!r}, version {head.get('version')!r})")
    file_crs = _crs_from_url(head.get("metadata", {}).get("referenceSystem"))
    world, items = _world_vertices(docs)
    objects = {oid: (obj, base) for oid, obj, base in items}
    frame = LocalFrame.around(world.min(axis=0) if len(world) else np.zeros(3))
    local = frame.to_local(world)
    split = {
        oid
        for oid, (obj, _) in objects.items()
        if obj.get("type") == "Building" and _read_as_parts(obj, objects, parts)
    }
    buildings, skipped = [], {}
    for oid, (obj, base) in objects.items():
        try:
            b = _city_object(oid, obj, base, objects, local, frame, split, skipped)
        except (IndexError, KeyError, TypeError, ValueError, AttributeError) as exc:
            # a vertex index beyond the vertex list, a ring that is no list of indices...
            raise InputError(f"{path}: CityObject {oid!r} has malformed geometry ({type(exc).__name__}: {exc})") from None
        if b is not None:
            buildings.append(b)
        elif isinstance(obj, dict) and obj.get("geometry") and not obj.get("parents"):
            _count(skipped, f"{obj.get('type')} object (not a building)")
    if not buildings:
        raise InputError(f"{path}: no Building with geometry in the file")
    meta = {"source": str(path), "version": str(head.get("version")), "skipped_geometries": skipped}
    if "referenceDate" in head.get("metadata", {}):
        meta["referenceDate"] = head["metadata"]["referenceDate"]
    return CityModel(buildings, crs or file_crs, frame, meta)


def solid_inventory(path: str | Path) -> tuple[list[tuple[str, str, str, Solid]], dict[str, int]]:
    """Every solid of every CityObject of a CityJSON file, whatever its type, for validation.

    Unlike :func:`read_cityjson`, which builds one model per Building, this reads each
    geometry as the file holds it: the exterior shell of every ``Solid``, and of every
    solid of a ``MultiSolid`` or ``CompositeSolid``, of every CityObject (Building,
    BuildingPart, BuildingInstallation, ...).

    Returns
    -------
    solids : list of (object id, object type, label, Solid)
        ``label`` is ``"LoD <lod>"``, with ``" solid <k>"`` for the k-th solid of a
        MultiSolid / CompositeSolid.
    others : dict
        Geometries that are not solids (MultiSurface, CompositeSurface, ...), counted by type.

    Raises
    ------
    InputError
        Not CityJSON, or a geometry indexing vertices that do not exist.
    """
    from recon3d.errors import InputError
    from recon3d.io import require_file

    path = require_file(path, "CityJSON")
    docs = _read_documents(path)
    if not docs or not all(isinstance(d, dict) for d in docs):
        raise InputError(f"{path}: not CityJSON (the top level is not a JSON object)")
    if docs[0].get("type") != "CityJSON":
        raise InputError(f"{path}: not CityJSON (type {docs[0].get('type')!r})")
    solids, others = [], {}
    world, items = _world_vertices(docs)
    local = world - (world.min(axis=0) if len(world) else 0.0)
    for oid, obj, base in items:
        for geom in obj.get("geometry", []) if isinstance(obj, dict) else []:
            kind, lod = geom.get("type"), str(geom.get("lod"))
            b = geom.get("boundaries", [])
            if kind == "Solid":
                shells = [("", b[0])] if b else []
            elif kind in ("MultiSolid", "CompositeSolid"):
                shells = [(f" solid {k}", solid[0]) for k, solid in enumerate(b) if solid]
            else:
                others[kind] = others.get(kind, 0) + 1
                continue
            for suffix, shell in shells:
                try:
                    surfaces = [[np.asarray(r, dtype=np.int64) + base for r in surface] for surface in shell]
                    kinds = [_kind_by_normal(local, rings) for rings in surfaces]
                    solids.append((oid, obj.get("type", "?"), f"LoD {lod}{suffix}", _solid(local, surfaces, kinds)))
                except (IndexError, TypeError, ValueError) as exc:
                    raise InputError(f"{path}: CityObject {oid!r} has malformed geometry ({type(exc).__name__}: {exc})") from None
    return solids, others


def _world_vertices(docs: list[dict]) -> tuple[np.ndarray, list[tuple[str, Any, int]]]:
    """All vertices of a CityJSON file or sequence in world coordinates, (n, 3), and its
    city objects as (id, object, offset of its document's vertices), in file order."""
    head = docs[0]
    scale = np.asarray(head.get("transform", {}).get("scale", [1, 1, 1]), dtype=np.float64)
    translate = np.asarray(head.get("transform", {}).get("translate", [0, 0, 0]), dtype=np.float64)
    blocks, items, offset = [], [], 0
    for doc in docs:
        block = np.asarray(doc.get("vertices", []), dtype=np.float64).reshape(-1, 3)
        items += [(oid, obj, offset) for oid, obj in doc.get("CityObjects", {}).items()]
        blocks.append(block)
        offset += len(block)
    return (np.concatenate(blocks) * scale + translate if offset else np.zeros((0, 3))), items


def _city_object(oid, obj, base, objects, local, frame, split, skipped) -> Building | None:
    """The :class:`Building` one CityObject is read as (None: not read as one)."""
    if not isinstance(obj, dict):
        raise TypeError("the CityObject is not a JSON object")
    kind = obj.get("type")
    if kind == "Building" and oid not in split:
        return _building(oid, obj, base, objects, local, frame, None, skipped)
    if kind == "BuildingPart" and obj.get("parents") and obj["parents"][0] in split:
        parent = obj["parents"][0]
        block_attrs = objects[parent][0].get("attributes", {})
        inherited = {k: v for k, v in block_attrs.items() if k not in BLOCK_KEYS}
        b = _building(oid, obj, base, objects, local, frame, inherited, skipped)
        if b is not None:
            b.parent = parent
        return b
    return None


def _read_documents(path: Path) -> list[dict]:
    from recon3d.errors import InputError

    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text file ({exc.reason} at byte {exc.start}); CityJSON is UTF-8 JSON") from None
    try:
        if path.suffix == ".jsonl":
            return [json.loads(line) for line in text.splitlines() if line.strip()]
        return [json.loads(text)]
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None


def _crs_from_url(url: str | None) -> pyproj.CRS | None:
    if not url:
        return None
    code = url.rstrip("/").split("/")
    try:
        return pyproj.CRS.from_user_input(f"{code[-3]}:{code[-1]}")
    except (pyproj.exceptions.CRSError, IndexError):
        log.warning("CityJSON referenceSystem %s not understood; CRS left unset", url)
        return None


def _read_as_parts(obj: dict, objects: dict, parts: bool | None) -> bool:
    """Whether a Building is read as its BuildingParts (see :func:`read_cityjson`)."""
    children = [
        c
        for c in obj.get("children", [])
        if c in objects and objects[c][0].get("type") == "BuildingPart"
    ]
    if parts is None:
        count = (obj.get("attributes") or {}).get("parts")
        return bool(children) and isinstance(count, int) and count == len(children)
    return parts and len(children) >= 2


def _building(
    oid: str,
    obj: dict,
    base: int,
    objects: dict,
    local: np.ndarray,
    frame: LocalFrame,
    inherited: dict | None,
    skipped: dict,
) -> Building | None:
    """One Building from a CityObject and its BuildingPart children (their vertex offsets applied).

    ``inherited`` attributes (a block's) come first; the object's own replace them.
    Geometries not read into the building are counted in ``skipped`` by type and reason.
    """
    import shapely

    parts = [(obj, base)] + [objects[c] for c in obj.get("children", []) if c in objects]
    solids: dict[str, Solid] = {}
    surface_sets: dict[str, Solid] = {}
    plan_ground, plan_all = [], []
    for part, offset in parts:
        for geom in part.get("geometry", []):
            surfaces, kinds = _surfaces(geom, offset)
            for rings, kind in zip(surfaces, kinds, strict=True):
                poly = _plan(local, rings)
                if poly is not None:
                    plan_all.append(poly)
                    if kind == "GroundSurface":
                        plan_ground.append(poly)
            gtype, lod = geom.get("type"), str(geom.get("lod"))
            target = solids if gtype == "Solid" else surface_sets if gtype in SURFACE_TYPES else None
            if target is None or not surfaces or lod in target:
                _count(skipped, f"{gtype} ({'another geometry of its LoD' if target is not None and surfaces else 'not read'})")
                continue
            kinds = [k or _kind_by_normal(local, rings) for k, rings in zip(kinds, surfaces, strict=True)]
            target[lod] = _solid(local, surfaces, kinds, "Solid" if gtype == "Solid" else "MultiSurface")
    for lod, surface_set in surface_sets.items():  # a Solid of the same LoD says more
        if lod in solids:
            _count(skipped, f"{surface_set.kind} (beside a Solid of its LoD)")
        else:
            solids[lod] = surface_set
    plans = plan_ground or plan_all
    if not plans:
        return None
    footprint = shapely.make_valid(shapely.union_all(plans))
    polys = [g for g in getattr(footprint, "geoms", [footprint]) if g.geom_type == "Polygon"]
    if not polys:
        return None
    footprint = shapely.affinity.translate(max(polys, key=lambda p: p.area), *frame.origin[:2])
    attrs = {**(inherited or {}), **obj.get("attributes", {})}
    z = frame.to_world(local[np.unique(np.concatenate([_flat(s) for s in _all_rings(parts)]))])[:, 2] if solids or plans else np.array([np.nan])
    ground_z = float(attrs.pop("ground_z", np.min(z)))
    roof_z = float(attrs.pop("roof_z", np.max(z)))
    attrs.pop("height", None)
    status, reason = attrs.pop("status", "ok"), attrs.pop("reason", None)
    return Building(oid, shapely.orient_polygons(footprint), ground_z, roof_z, solids, status, reason, attrs)


def _count(counts: dict, key: str) -> None:
    counts[key] = counts.get(key, 0) + 1


def _surfaces(geom: dict, offset: int) -> tuple[list[list[np.ndarray]], list[str | None]]:
    """Surfaces (rings of vertex indices, offset applied) and their semantic types."""
    kind = geom.get("type")
    b = geom.get("boundaries", [])
    sem = geom.get("semantics", {})
    if kind == "Solid":
        shells, values = b[:1], (sem.get("values") or [None])[:1]
    elif kind in ("MultiSurface", "CompositeSurface"):
        shells, values = [b], [sem.get("values")]
    else:  # MultiSolid / CompositeSolid: first solid's outer shell
        shells, values = ([b[0][0]], [(sem.get("values") or [[None]])[0][0]]) if b else ([], [])
    types = [s.get("type") for s in sem.get("surfaces", [])]
    surfaces, kinds = [], []
    for shell, vals in zip(shells, values, strict=True):
        for i, surface in enumerate(shell):
            surfaces.append([np.asarray(r, dtype=np.int64) + offset for r in surface])
            v = vals[i] if vals is not None and i < len(vals) else None
            kinds.append(types[v] if v is not None and v < len(types) else None)
    return surfaces, kinds


def _kind_by_normal(local: np.ndarray, rings: list[np.ndarray]) -> str:
    """Semantic type of a surface without semantics: facing down is ground, steep is wall."""
    from recon3d.core.city import newell_normal

    n = newell_normal(local[rings[0]])
    nz = n[2] / (np.linalg.norm(n) or 1.0)
    return "GroundSurface" if nz < -0.9 else "WallSurface" if abs(nz) < 0.17 else "RoofSurface"


def _plan(local: np.ndarray, rings: list[np.ndarray]):
    import shapely

    if len(rings[0]) < 3:
        return None
    poly = shapely.Polygon(local[rings[0], :2], [local[r, :2] for r in rings[1:] if len(r) >= 3])
    poly = shapely.make_valid(poly)
    return poly if poly.area > 1e-6 else None


def _solid(local: np.ndarray, surfaces: list[list[np.ndarray]], kinds: list[str], kind: str = "Solid") -> Solid:
    used = np.unique(np.concatenate([np.concatenate(s) for s in surfaces]))
    remap = np.full(len(local), -1, np.int64)
    remap[used] = np.arange(len(used))
    return Solid(local[used], [[remap[r] for r in s] for s in surfaces], kinds, kind)


def _all_rings(parts):
    for part, offset in parts:
        for geom in part.get("geometry", []):
            yield from _surfaces(geom, offset)[0]


def _flat(surface: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(surface)
