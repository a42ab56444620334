"""Vector files (GeoJSON, GeoPackage, Shapefile) to and from shapely, through pyogrio (GDAL)."""

from __future__ import annotations

import contextlib
import logging
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyogrio
import pyproj
import shapely

from recon3d.core.geo import check_area_of_use, crs_name
from recon3d.errors import CRSError, InputError
from recon3d.io import atomic_path, require_file

log = logging.getLogger(__name__)

__all__ = ["Footprint", "read_footprints", "read_terrain_vectors", "write_features"]


@dataclass
class Footprint:
    """A 2-D building outline read from a vector file."""

    id: str
    polygon: shapely.Polygon
    attributes: dict[str, Any] = field(default_factory=dict)


def read_footprints(
    path: str | Path, *, crs: pyproj.CRS, id_field: str | None = None
) -> tuple[list[Footprint], list[str]]:
    """Read building outlines and bring them into ``crs``.

    Multipolygons become one footprint per part (``id-1``, ``id-2``...); invalid
    rings are repaired with ``shapely.make_valid``; Z values are dropped; features
    without area are skipped.

    Returns
    -------
    footprints : list of Footprint
    notes : list of str
        One line per repaired or skipped feature, for run.json.

    Raises
    ------
    InputError
        Unreadable file or no polygon in it.
    CRSError
        The file has no CRS.
    """
    path = require_file(path, "footprints")
    if _is_cityjson(path):
        return _cityjson_footprints(path, crs)
    meta, geoms, fields = _read_layer(path, crs)
    geoms = shapely.force_2d(geoms)
    names = list(meta["fields"])
    id_field = id_field or next((n for n in names if n.lower() in ("id", "identifiant", "fid", "gml_id", "identificatie")), None)
    footprints, notes = [], []
    for i, geom in enumerate(geoms):
        attrs = {n: _plain(fields[j][i]) for j, n in enumerate(names)}
        fid = str(attrs.get(id_field, i)) if id_field else str(i)
        parts, note = _polygon_parts(geom)
        if note:
            notes.append(f"{path.name} feature {fid}: {note}")
        suffix = len(parts) > 1
        footprints += [
            Footprint(f"{fid}-{k + 1}" if suffix else fid, p, attrs) for k, p in enumerate(parts)
        ]
    if not footprints:
        raise InputError(f"{path}: no polygon with an area in the file")
    return footprints, notes


def read_terrain_vectors(path: str | Path, *, crs: pyproj.CRS) -> tuple[list[np.ndarray], np.ndarray]:
    """Read 3-D breaklines and spot heights (survey altimetry) from a vector file.

    Returns
    -------
    lines : list of (k, 3) float arrays
        Vertices of every (multi)line, x and y in ``crs``.
    points : (m, 3) float
        Every point feature.

    Raises
    ------
    InputError
        Unreadable file, or features without Z values (a breakline needs heights).
    CRSError
        The file has no CRS.
    """
    path = require_file(path, "terrain vectors")
    _, geoms, _ = _read_layer(path, crs)
    if not shapely.has_z(geoms).all():
        raise InputError(f"{path}: every breakline and point needs Z values (heights)")
    parts = shapely.get_parts(geoms)
    kinds = shapely.get_type_id(parts)
    lines = [shapely.get_coordinates(g, include_z=True) for g in parts[np.isin(kinds, (1, 2))]]
    points = shapely.get_coordinates(parts[kinds == 0], include_z=True).reshape(-1, 3)
    if not lines and not len(points):
        raise InputError(f"{path}: no line or point features")
    return lines, points


#: GDAL driver and layer options per suffix. GeoJSON keeps the data's CRS (RFC7946=NO:
#: RFC 7946 would reproject to WGS84) with a "crs" member when it has an EPSG code; a
#: GeoPackage carries any CRS, as its EPSG code or its WKT.
VECTOR_FORMATS = {
    ".geojson": ("GeoJSON", {"RFC7946": "NO", "WRITE_BBOX": "YES"}),
    ".gpkg": ("GPKG", {}),
}


def write_features(
    path: str | Path,
    geometries: list[shapely.Geometry],
    properties: list[dict[str, Any]],
    crs: pyproj.CRS | None,
    *,
    date: str | None = None,
) -> None:
    """Write polygons and their properties as GeoJSON or GeoPackage (by suffix).

    Parameters
    ----------
    path : path-like
        ``.geojson`` or ``.gpkg``.
    geometries, properties : lists of one item per feature
    crs : pyproj.CRS or None
    date : str, optional
        ISO date of the data, the GeoPackage's ``last_change`` (default today, or the
        day of ``SOURCE_DATE_EPOCH``): GDAL would write the time of writing, and the
        same input would no longer give the same bytes.
    """
    driver, options = VECTOR_FORMATS[Path(path).suffix.lower()]
    keys = list(dict.fromkeys(k for p in properties for k in p))
    columns = [np.array([_plain(p.get(k)) for p in properties], dtype=object) for k in keys]
    columns = [_typed(c) for c in columns]
    wkb = np.array(shapely.to_wkb(np.array(geometries, dtype=object)), dtype=object)
    with atomic_path(path) as tmp, _gdal_date(date):
        tmp.unlink()
        pyogrio.raw.write(
            tmp,
            wkb,
            columns,
            fields=keys,
            geometry_type="Polygon" if all(g.geom_type == "Polygon" for g in geometries) else "Unknown",
            crs=crs.to_wkt() if crs is not None else None,
            driver=driver,
            layer=Path(path).name.split(".")[0],  # not the temporary name: same input, same bytes
            layer_options=options,
        )


@contextlib.contextmanager
def _gdal_date(date: str | None):
    """GDAL's ``OGR_CURRENT_DATE`` (the GeoPackage ``last_change``) set to ``date`` at midnight UTC."""
    from recon3d.core.dates import today

    key = "OGR_CURRENT_DATE"
    before = pyogrio.get_gdal_config_option(key)
    pyogrio.set_gdal_config_options({key: f"{date or today()}T00:00:00.000Z"})
    try:
        yield
    finally:
        pyogrio.set_gdal_config_options({key: before})


def _is_cityjson(path: Path) -> bool:
    if path.suffix.lower() not in (".json", ".jsonl"):
        return False
    with path.open("rb") as f:
        return b'"CityJSON' in f.read(4096)


def _cityjson_footprints(path: Path, crs: pyproj.CRS) -> tuple[list[Footprint], list[str]]:
    """Plan-view outlines of the buildings of a CityJSON file, in ``crs``."""
    from recon3d.io.cityjson import read_cityjson

    city = read_cityjson(path)
    if city.crs is None:
        raise CRSError(f"{path}: the CityJSON file has no referenceSystem in its metadata")
    geoms = np.array([b.footprint for b in city], dtype=object)
    if not _same_horizontal(city.crs, crs):
        t = pyproj.Transformer.from_crs(_horizontal(city.crs), _horizontal(crs), always_xy=True)
        geoms = shapely.transform(geoms, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1])))
    attrs = [dict(b.attributes, roof_z=b.roof_z, ground_z=b.ground_z) for b in city]
    return [Footprint(b.id, g, a) for b, g, a in zip(city, geoms, attrs, strict=True)], []


def _read_layer(path: Path, crs: pyproj.CRS) -> tuple[dict, np.ndarray, list]:
    """Geometries of the first layer in ``crs`` (heights kept), with the layer's metadata and fields.

    Raises CRSError for a layer without CRS, or with longitude/latitude declared (as
    GeoJSON without a crs member implies) but projected numbers inside.
    """
    try:
        with warnings.catch_warnings():  # GDAL's notes (unclosed rings...) surface as the errors below
            warnings.simplefilter("ignore", RuntimeWarning)
            meta, _, wkb, fields = pyogrio.raw.read(path)
    except Exception as exc:
        raise InputError(f"{path}: cannot read vector file ({exc})") from None
    if meta.get("crs") is None:
        raise CRSError(f"{path}: the file has no CRS (add a .prj or a crs member)")
    src = pyproj.CRS.from_user_input(meta["crs"])
    geoms = shapely.from_wkb(wkb, on_invalid="ignore")  # None where the geometry cannot be built
    broken = [i for i, (g, raw) in enumerate(zip(geoms, wkb, strict=True)) if g is None and raw is not None]
    if broken:
        raise InputError(
            f"{path}: feature {broken[0]} (of {len(broken)} broken) has a geometry that cannot be built, "
            "e.g. a ring of fewer than 4 points or not closed; repair it (QGIS: Fix geometries)"
        )
    if src.is_geographic:
        b = shapely.bounds(geoms)
        if np.nanmax(np.abs(b[:, [0, 2]])) > 180 or np.nanmax(np.abs(b[:, [1, 3]])) > 90:
            raise CRSError(
                f"{path}: the file's CRS is {crs_name(src)} (longitude/latitude; GeoJSON without "
                "a crs member means WGS84) but its coordinates are projected; write the CRS into the file"
            )
    bounds = shapely.bounds(geoms)
    if len(bounds) and np.isfinite(bounds).any():
        check_area_of_use(src, np.nanmin(bounds[:, :2], axis=0), np.nanmax(bounds[:, 2:], axis=0), source=str(path))
    if not _same_horizontal(src, crs):
        log.info("reprojecting %s from %s to %s", path.name, crs_name(src), crs_name(crs))
        t = pyproj.Transformer.from_crs(_horizontal(src), _horizontal(crs), always_xy=True)
        geoms = shapely.transform(
            geoms, lambda xyz: np.column_stack([*t.transform(xyz[:, 0], xyz[:, 1]), xyz[:, 2:]]), include_z=True
        )
    return meta, geoms, fields


def _polygon_parts(geom) -> tuple[list[shapely.Polygon], str | None]:
    if geom is None or geom.is_empty:
        return [], "empty geometry skipped"
    note = None
    if not geom.is_valid:
        note = f"invalid polygon repaired ({shapely.is_valid_reason(geom)})"
        geom = shapely.make_valid(geom)
    parts = [g for g in getattr(geom, "geoms", [geom]) if g.geom_type == "Polygon" and g.area > 0]
    if not parts and geom.geom_type == "GeometryCollection":
        parts = [p for g in geom.geoms for p in getattr(g, "geoms", [g]) if p.geom_type == "Polygon" and p.area > 0]
    if not parts:
        return [], f"{geom.geom_type} without area skipped"
    return [shapely.orient_polygons(p) for p in parts], note


def _horizontal(crs: pyproj.CRS) -> pyproj.CRS:
    return crs.sub_crs_list[0] if crs.is_compound else crs


def _same_horizontal(a: pyproj.CRS, b: pyproj.CRS) -> bool:
    return _horizontal(a).equals(_horizontal(b), ignore_axis_order=True)


def _plain(v: Any) -> Any:
    """numpy scalars to Python values; NaN to None."""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def _typed(column: np.ndarray) -> np.ndarray:
    """Give pyogrio a typed column where every value shares a numeric type."""
    values = [v for v in column if v is not None]
    if values and all(isinstance(v, bool) for v in values):
        return column.astype(str)
    if values and all(isinstance(v, int) and not isinstance(v, bool) for v in values) and len(values) == len(column):
        return column.astype(np.int64)
    if values and all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return np.array([np.nan if v is None else float(v) for v in column])
    return np.array([None if v is None else str(v) for v in column], dtype=object)

