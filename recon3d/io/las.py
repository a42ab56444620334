"""LAS/LAZ point clouds through laspy (LAZ by lazrs)."""

from __future__ import annotations

import logging
from pathlib import Path

import laspy
import numpy as np
import pyproj
from laspy.vlrs.known import WktCoordinateSystemVlr

from recon3d.core.geo import check_area_of_use, crs_name
from recon3d.core.pointcloud import PointCloud
from recon3d.errors import CRSError, InputError
from recon3d.io import atomic_path, require_file

log = logging.getLogger(__name__)

__all__ = ["las_date", "las_tiles", "las_wkt", "read_las", "read_las_tiles", "write_las"]

#: Standard LAS dimensions carried through recon3d (extra-bytes dimensions are dropped).
KEPT_DIMENSIONS = (
    "intensity",
    "return_number",
    "number_of_returns",
    "classification",
    "scan_angle_rank",
    "scan_angle",
    "user_data",
    "point_source_id",
    "gps_time",
    "red",
    "green",
    "blue",
    "nir",
)


def read_las(path: str | Path, *, crs: pyproj.CRS | None = None) -> PointCloud:
    """Read a LAS or LAZ file.

    Parameters
    ----------
    path : path-like
    crs : pyproj.CRS, optional
        CRS to use when the file has none. When the file has one and ``crs``
        differs, a :class:`CRSError` is raised rather than guessing which is right.

    Returns
    -------
    PointCloud
        xyz (n, 3) float64 in file units and the kept standard dimensions.

    Raises
    ------
    InputError
        Missing, truncated or corrupt file, or a cloud without points.
    CRSError
        No CRS in the file and none given, or a conflicting one given.
    """
    path = require_file(path, "point cloud")
    _check_point_count(path)
    try:
        las = laspy.read(path)
        xyz = np.empty((len(las.points), 3))  # filled one axis at a time: one scaled copy alive at once
        xyz[:, 0] = las.x
        xyz[:, 1] = las.y
        xyz[:, 2] = las.z
    except Exception as exc:  # laspy, lazrs and numpy all raise on a damaged file
        raise InputError(f"{path}: cannot read LAS/LAZ ({_short(exc)})") from None
    if len(xyz) == 0:
        raise InputError(f"{path}: the point cloud is empty (0 points)")
    if not np.isfinite(xyz).all():
        raise InputError(f"{path}: {int((~np.isfinite(xyz)).any(axis=1).sum())} points have NaN or infinite coordinates")
    names = set(las.point_format.dimension_names)
    attributes = {n: np.asarray(las[n]).copy() for n in KEPT_DIMENSIONS if n in names}
    file_crs = _header_crs(las, path)
    resolved = _resolve_crs(file_crs, crs, path)
    if resolved is not None:
        check_area_of_use(resolved, xyz.min(axis=0), xyz.max(axis=0), source=str(path))
    return PointCloud(xyz, attributes, resolved)


#: Suffixes of the point files a folder or a glob of tiles is made of.
LAS_SUFFIXES = (".las", ".laz")


def las_tiles(inputs: list[str | Path]) -> list[Path] | None:
    """The LAS/LAZ files a list of inputs names, or None when it names none.

    Each input is a LAS/LAZ file, a folder (its ``*.las`` and ``*.laz``, not its
    sub-folders) or a glob pattern the shell did not expand (``"tiles/*.laz"``).
    Files named twice count once; the order is the paths'.

    Raises
    ------
    InputError
        A folder or pattern with no LAS/LAZ file, or LAS/LAZ files mixed with other inputs.
    """
    import glob

    found, other = [], []
    for given in map(str, inputs):
        path = Path(given)
        if not path.exists() and glob.has_magic(given):
            hits = [Path(p) for p in glob.glob(given) if Path(p).suffix.lower() in LAS_SUFFIXES]
            if not hits:
                raise InputError(f"{given}: no LAS/LAZ file matches the pattern")
            found += hits
        elif path.suffix.lower() in LAS_SUFFIXES:
            found.append(path)
        elif path.is_dir() and any(p.suffix.lower() in LAS_SUFFIXES for p in path.iterdir()):
            found += [p for p in path.iterdir() if p.suffix.lower() in LAS_SUFFIXES and p.is_file()]
        else:
            other.append(given)
    if found and other:
        raise InputError(f"{other[0]}: not a LAS/LAZ tile, given with the point files {found[0].name}...; "
                         "give tiles of one survey, or one other input")
    return sorted(set(found), key=lambda p: str(p)) or None


def read_las_tiles(paths: list[Path], *, crs: pyproj.CRS | None = None) -> tuple[PointCloud, int]:
    """Read the LAS/LAZ tiles of one survey as one cloud.

    The tiles must share their CRS and point format; a tile whose header repeats
    another's bounds and point count is the same tile given twice. Points two tiles
    both hold (buffers around delivered tiles) are kept once. The cloud holds
    the tiles in the order of their lower-left corners (then names), so the same set
    of files gives the same cloud however it was named.

    Raises
    ------
    InputError
        A tile missing or damaged (named), different point formats, a duplicate tile,
        or more points than memory holds.
    CRSError
        Tiles in different CRSs.
    """
    from recon3d.core.memory import require_memory

    headers = {}
    for path in paths:
        path = require_file(path, "point cloud")
        _check_point_count(path)
        try:
            with laspy.open(path) as reader:
                h = reader.header
                headers[path] = (tuple(np.round(h.mins, 3)), tuple(np.round(h.maxs, 3)), int(h.point_count),
                                 int(h.point_format.id), int(h.point_format.size))
        except Exception as exc:
            raise InputError(f"{path}: cannot read LAS/LAZ header ({_short(exc)})") from None
    order = sorted(headers, key=lambda p: (headers[p][0][:2], str(p)))
    first = order[0]
    for path in order[1:]:
        if headers[path][3] != headers[first][3]:
            raise InputError(f"{path}: point format {headers[path][3]}, but {first.name} has {headers[first][3]}; "
                             "tiles of one survey share their point format")
    seen: dict = {}
    for path in order:
        key = headers[path][:3]
        if key in seen:
            raise InputError(f"{path}: the same tile as {seen[key].name} (same bounds and point count); give it once")
        seen[key] = path
    total = sum(h[2] for h in headers.values())
    require_memory(total * (headers[first][4] + 64), f"reading the {total} points of {len(order)} tiles",
                   "give fewer tiles at a time", source=first.parent)
    clouds = []
    for path in order:
        cloud = read_las(path, crs=crs)
        if clouds and not _same_crs(cloud.crs, clouds[0].crs):
            raise CRSError(f"{path}: CRS {crs_name(cloud.crs)}, but {first.name} is in {crs_name(clouds[0].crs)}; "
                           "reproject the tiles to one CRS")
        clouds.append(cloud)
    names = [n for n in clouds[0].attributes if all(n in c.attributes for c in clouds)]
    attributes = {n: np.concatenate([c.attributes[n] for c in clouds]) for n in names}
    log.info("%d tiles, %d points", len(clouds), total)
    cloud = PointCloud(np.concatenate([c.xyz for c in clouds]), attributes, clouds[0].crs)
    first = _first_of_each(cloud)
    return cloud[first], int((~first).sum())


def _first_of_each(cloud: PointCloud) -> np.ndarray:
    """(n,) bool: every point but the repeats of one already seen (same x, y, z and GPS
    time), which tiles delivered with overlapping buffers hold twice."""
    keys = [cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]]
    if "gps_time" in cloud.attributes:
        keys.append(cloud.attributes["gps_time"])
    order = np.lexsort(keys[::-1])
    rows = np.column_stack([k[order] for k in keys])
    repeat = np.zeros(len(cloud), bool)
    repeat[order[1:]] = (rows[1:] == rows[:-1]).all(axis=1)
    return ~repeat


#: Largest compression ratio believed of a LAZ file: a header claiming more points than
#: this many times the file could hold is damaged (reading it would allocate them all).
MAX_LAZ_RATIO = 30


def _check_record_counts(path: Path) -> None:
    """Refuse a header whose VLR or EVLR count the file cannot hold (laspy would try to read
    millions of them), from the raw header fields of the LAS specification."""
    import struct

    with open(path, "rb") as f:
        head = f.read(247)
    if len(head) < 104 or head[:4] != b"LASF":
        return  # not LAS at all: laspy says so
    header_size, start, n_vlr = struct.unpack_from("<HII", head, 94)
    if n_vlr * 54 > max(start - header_size, 0):  # a VLR header alone is 54 bytes
        raise InputError(f"{path}: the header claims {n_vlr} variable-length records in {start - header_size} bytes: damaged")
    if head[24:26] == b"\x01\x04" and len(head) >= 247:  # LAS 1.4: extended VLRs at the end
        evlr_start, n_evlr = struct.unpack_from("<QI", head, 235)
        if n_evlr and n_evlr * 60 > max(path.stat().st_size - evlr_start, 0):
            raise InputError(f"{path}: the header claims {n_evlr} extended records beyond the file's end: damaged")


def _check_point_count(path: Path) -> None:
    """Refuse a header whose point count the file cannot hold, or memory cannot, before reading."""
    from recon3d.core.memory import require_memory

    _check_record_counts(path)
    try:
        with laspy.open(path) as reader:
            header = reader.header
            count, size = int(header.point_count), int(header.point_format.size)
            start, compressed = int(header.offset_to_point_data), bool(header.are_points_compressed)
    except Exception as exc:  # a header laspy cannot parse: read_las reports it below
        raise InputError(f"{path}: cannot read LAS/LAZ header ({_short(exc)})") from None
    data = max(path.stat().st_size - start, 0)
    room = data * (MAX_LAZ_RATIO if compressed else 1) // max(size, 1)
    if count > room:
        raise InputError(f"{path}: the header claims {count} points but the file holds at most {room}: truncated or damaged")
    # the records, float64 coordinates and the kept attributes
    require_memory(count * (size + 64), f"reading its {count} points", "cut the cloud into tiles", source=path)


def las_date(path: str | Path) -> str | None:
    """The header's file creation date (ISO ``YYYY-MM-DD``), None when unset or unreadable.

    For a survey tile this is the day the data was compiled, the natural
    ``referenceDate`` of a city model built from it (and the same on every run).
    """
    try:
        with laspy.open(path) as reader:
            day = reader.header.creation_date
    except Exception:  # read_las has already reported a broken file
        return None
    return day.isoformat() if day is not None else None


def las_wkt(crs: pyproj.CRS) -> str:
    """The WKT of a LAS 1.4 CRS record: WKT1 as GDAL writes it, what the LAS 1.4
    specification asks for and PDAL's writer writes, with the EPSG authority when the
    CRS has one; WKT2 for a CRS that WKT1 cannot express."""
    try:
        wkt = crs.to_wkt("WKT1_GDAL")
    except pyproj.exceptions.CRSError:
        wkt = None
    return wkt or crs.to_wkt()


def write_las(cloud: PointCloud, path: str | Path) -> None:
    """Write a cloud as LAS 1.4 (LAZ when the suffix is .laz), CRS as WKT in the header
    (:func:`las_wkt`).

    Point format 6 without colour, 7 with RGB, 8 with RGB and NIR.
    """
    a = cloud.attributes
    fmt = 8 if "nir" in a and "red" in a else 7 if "red" in a else 6
    header = laspy.LasHeader(point_format=fmt, version="1.4")
    mins = cloud.xyz.min(axis=0)
    header.offsets = np.floor(mins)
    header.scales = np.array([0.001, 0.001, 0.001])
    if cloud.crs is not None:
        header.vlrs.append(WktCoordinateSystemVlr(las_wkt(cloud.crs)))
        header.global_encoding.wkt = True
    las = laspy.LasData(header)
    las.x, las.y, las.z = cloud.xyz[:, 0], cloud.xyz[:, 1], cloud.xyz[:, 2]
    names = set(las.point_format.dimension_names)
    for name, values in a.items():
        if name in names and name not in ("scan_angle_rank",):
            las[name] = values
    if "scan_angle_rank" in a and "scan_angle" not in a:
        las["scan_angle"] = np.round(a["scan_angle_rank"].astype(np.float64) / 0.006).astype(np.int16)
    with atomic_path(path) as tmp:
        las.write(tmp)


def _header_crs(las: laspy.LasData, path: Path) -> pyproj.CRS | None:
    try:
        return las.header.parse_crs()
    except Exception as exc:  # unreadable GeoTIFF keys or WKT: treat as absent, say so
        log.warning("%s: CRS in the header cannot be parsed (%s); treating it as missing", path, _short(exc))
        return None


def _resolve_crs(file_crs: pyproj.CRS | None, user_crs: pyproj.CRS | None, path: Path) -> pyproj.CRS:
    if file_crs is None and user_crs is None:
        raise CRSError(f"{path}: the file has no CRS; give one with --crs (for example --crs EPSG:7415)")
    if file_crs is None:
        return user_crs
    if user_crs is not None and not _same_crs(file_crs, user_crs):
        raise CRSError(
            f"{path}: the file's CRS is {crs_name(file_crs)} but --crs says {crs_name(user_crs)}; "
            "leave out --crs or reproject the file"
        )
    return user_crs if user_crs is not None else file_crs


def _same_crs(a: pyproj.CRS, b: pyproj.CRS) -> bool:
    """Same CRS, or the same horizontal CRS when only one of them has a vertical part."""
    if a.equals(b, ignore_axis_order=True):
        return True
    ha = a.sub_crs_list[0] if a.is_compound else a
    hb = b.sub_crs_list[0] if b.is_compound else b
    return ha.equals(hb, ignore_axis_order=True) and (a.is_compound != b.is_compound)


def _short(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:200] if text else type(exc).__name__
