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
  ``geographicalExtent`` in world coordinates, ``referenceDate``, ``title`` and,
  when given, ``identifier`` and ``pointOfContact``;
- a building that could not be built is still written, with ``"geometry": []`` and
  its ``status`` / ``reason`` attributes, so a user sees every footprint.
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
from recon3d.core.geo import crs_authority, crs_name, crs_units
from recon3d.errors import CRSError
from recon3d.io import atomic_path

log = logging.getLogger(__name__)

__all__ = [
    "building_attributes",
    "cityjson_dict",
    "crs_url",
    "quantisation_scale",
    "write_cityjson",
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
        Two buildings share an id (one would silently replace the other).
    """
    ids = [b.id for b in city.buildings]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise ValueError(f"duplicate building ids cannot be written to CityJSON: {dup[:5]}")
    origin = np.asarray(city.frame.origin, dtype=np.float64)
    scale = quantisation_scale(city.crs)
    solids = [(b, lod, s) for b in city.buildings for lod, s in _sorted_solids(b)]
    vertices, remaps = _quantise([s.vertices for _, _, s in solids], scale)
    geometry: dict[str, list] = {b.id: [] for b in city.buildings}
    for (b, lod, solid), remap in zip(solids, remaps, strict=True):
        geom = _solid_geometry(solid, lod, remap)
        if geom is None:
            log.warning("building %s: LoD %s solid has no valid surface, not written", b.id, lod)
        else:
            geometry[b.id].append(geom)
    objects = {
        b.id: {"type": "Building", "attributes": building_attributes(b), "geometry": geometry[b.id]}
        for b in city.buildings
    }
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
    uniq, first, inverse = np.unique(q, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[inverse.reshape(-1)]
    ends = np.cumsum([len(v) for v in vertex_sets])[:-1]
    return uniq[order], np.split(index, ends)


def _solid_geometry(solid: Solid, lod: str, remap: np.ndarray) -> dict | None:
    """One CityJSON ``Solid`` geometry object, or None when no surface survives.

    Rings are re-indexed into the file's vertex list; vertices that quantisation
    merged are removed from rings (consecutive repeats), and rings left with fewer
    than 3 vertices are dropped (a surface whose outer ring goes is dropped).
    """
    surfaces, kinds = [], []
    for rings, kind in zip(solid.surfaces, solid.semantics, strict=True):
        clean = [_clean_ring(remap[r]) for r in rings]
        if len(clean[0]) < 3:
            continue
        surfaces.append([r.tolist() for r in clean if len(r) >= 3])
        kinds.append(kind)
    if not surfaces:
        return None
    types = list(dict.fromkeys(kinds))
    return {
        "type": "Solid",
        "lod": str(lod),
        "boundaries": [surfaces],
        "semantics": {
            "surfaces": [{"type": t} for t in types],
            "values": [[types.index(k) for k in kinds]],
        },
    }


def _clean_ring(ring: np.ndarray) -> np.ndarray:
    """(k,) ring without cyclically consecutive repeated vertices."""
    if len(ring) == 0:
        return ring
    return ring[ring != np.roll(ring, 1)] if len(np.unique(ring)) > 1 else ring[:1]


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
        "referenceDate": _dt.date.today().isoformat(),
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
    height reference travels with the file.
    """
    if crs is None:
        return None
    auth = crs_authority(crs)
    if not auth or auth[0].upper() not in _OGC_AUTHORITIES:
        log.warning("CityJSON: CRS %s has no EPSG/OGC code; referenceSystem omitted", crs_name(crs))
        return None
    return f"https://www.opengis.net/def/crs/{auth[0].upper()}/0/{auth[1]}"
