"""LAS/LAZ point clouds through laspy (LAZ by lazrs)."""

from __future__ import annotations

import datetime as _dt
import logging
from pathlib import Path

import laspy
import numpy as np
import pyproj
from laspy.vlrs.known import WktCoordinateSystemVlr

from recon3d.core.dates import today
from recon3d.core.geo import check_area_of_use, crs_name
from recon3d.core.pointcloud import PointCloud, column_bounds
from recon3d.errors import CRSError, InputError
from recon3d.io import atomic_path, require_file

log = logging.getLogger(__name__)

__all__ = ["LasStreamWriter", "check_header", "las_date", "las_tiles", "las_wkt", "read_las", "resolve_crs", "same_crs",
           "write_las"]

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
    if not scaling_is_finite(las.header) and not np.isfinite(xyz).all():
        raise InputError(f"{path}: {int((~np.isfinite(xyz)).any(axis=1).sum())} points have NaN or infinite coordinates")
    names = set(las.point_format.dimension_names)
    attributes = {n: np.asarray(las[n]).copy() for n in KEPT_DIMENSIONS if n in names}
    file_crs = _header_crs(las, path)
    resolved = resolve_crs(file_crs, crs, path)
    if resolved is not None:
        check_area_of_use(resolved, *column_bounds(xyz), source=str(path))
    return PointCloud(xyz, attributes, resolved)


def scaling_is_finite(header) -> bool:
    """Whether every coordinate of a LAS/LAZ file is finite: the integer records times
    finite scales plus finite offsets always are, so the header tells without a pass
    over the points (only a NaN or infinite scale or offset makes a NaN or infinite one)."""
    return bool(np.isfinite(header.scales).all() and np.isfinite(header.offsets).all()
                and (np.abs(header.scales) < 1e290).all())


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

    count, size = check_header(path)
    # the records, float64 coordinates and the kept attributes
    require_memory(count * (size + 64), f"reading its {count} points", "cut the cloud into tiles", source=path)


def check_header(path: Path) -> tuple[int, int]:
    """Refuse a header whose record counts or point count the file cannot hold (laspy
    would allocate them), before reading; its (point count, point record size)."""
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
    return count, size


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


def write_las(cloud: PointCloud, path: str | Path, date: str | None = None) -> None:
    """Write a cloud as LAS 1.4 (LAZ when the suffix is .laz), CRS as WKT in the header
    (:func:`las_wkt`).

    Point format 6 without colour, 7 with RGB, 8 with RGB and NIR; a stereo cloud's
    ``observed`` attribute as an extra-bytes dimension of that name (:data:`OBSERVED`);
    ``date`` as for :class:`LasStreamWriter`.
    """
    with LasStreamWriter(path, cloud.crs, list(cloud.attributes), cloud.bounds[0], date) as writer:
        writer.write(cloud)


class LasStreamWriter:
    """cloud.laz written a part at a time, in one pass, as :func:`write_las` writes it whole.

    The points go out in blocks of :data:`WRITE_BLOCK` (a whole number of LAZ chunks),
    so the file's bytes do not depend on how the parts were cut.

    Parameters
    ----------
    path : path-like
        Written under a temporary name, renamed on :meth:`close` (atomic).
    crs : pyproj.CRS or None
    names : list of str
        The attributes every part carries (the point format follows from them).
    mins : (3,) float
        Lowest corner of all the points (the header's offsets).
    date : str, optional
        ISO date for the header's creation date: the data's date, so that the same input
        gives the same bytes on any day (default :func:`~recon3d.core.dates.today`).
    """

    def __init__(self, path: str | Path, crs: pyproj.CRS | None, names: list[str], mins: np.ndarray,
                 date: str | None = None) -> None:
        fmt = 8 if "nir" in names and "red" in names else 7 if "red" in names else 6
        header = laspy.LasHeader(point_format=fmt, version="1.4")
        if "observed" in names:  # stereo: which points were matched, which filled in (written with the others)
            header.add_extra_dim(laspy.ExtraBytesParams(name="observed", type=np.uint8, description=OBSERVED))
        header.creation_date = _dt.date.fromisoformat(date or today())
        header.offsets = np.floor(np.asarray(mins, np.float64))
        header.scales = np.array([0.001, 0.001, 0.001])
        if crs is not None:
            header.vlrs.append(WktCoordinateSystemVlr(las_wkt(crs)))
            header.global_encoding.wkt = True
        self.header = header
        self._atomic = atomic_path(path)
        self._tmp = self._atomic.__enter__()
        self._writer = laspy.open(self._tmp, mode="w", header=header)
        self._parts: list[PointCloud] = []
        self._pending = 0

    def write(self, cloud: PointCloud) -> None:
        """Append the points of ``cloud`` (in the order they are to be in the file)."""
        self._parts.append(cloud)
        self._pending += len(cloud)
        while self._pending >= WRITE_BLOCK:
            self._flush(WRITE_BLOCK)

    def _flush(self, n: int) -> None:
        xyz = np.concatenate([p.xyz for p in self._parts])
        names = list(self._parts[0].attributes)
        attrs = {k: np.concatenate([p.attributes[k] for p in self._parts]) for k in names}
        block = PointCloud(xyz[:n], {k: v[:n] for k, v in attrs.items()})
        rest = PointCloud(xyz[n:], {k: v[n:] for k, v in attrs.items()})
        self._parts, self._pending = ([rest] if len(rest) else []), len(rest)
        las = laspy.LasData(self.header)
        las.x, las.y, las.z = block.xyz[:, 0], block.xyz[:, 1], block.xyz[:, 2]
        dims = set(las.point_format.dimension_names)
        a = block.attributes
        for name, values in a.items():
            if name in dims and name not in ("scan_angle_rank",):
                las[name] = values
        if "scan_angle_rank" in a and "scan_angle" not in a:
            las["scan_angle"] = np.round(a["scan_angle_rank"].astype(np.float64) / 0.006).astype(np.int16)
        self._writer.write_points(las.points)

    def close(self) -> None:
        """Write what is left and put the file in place."""
        if self._pending:
            self._flush(self._pending)
        self._writer.close()
        self._atomic.__exit__(None, None, None)

    def __enter__(self) -> LasStreamWriter:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        else:
            self._writer.close()
            self._atomic.__exit__(kind, value, tb)


#: Description of the extra-bytes dimension ``observed`` of a stereo cloud (at most 32
#: characters): 1 where the images matched the point, 0 where a hole was filled in.
OBSERVED = "1 matched, 0 filled-in guess"

#: Points written at a time by :class:`LasStreamWriter`: ten LAZ chunks of 50,000.
WRITE_BLOCK = 500_000


def _header_crs(las: laspy.LasData, path: Path) -> pyproj.CRS | None:
    try:
        return las.header.parse_crs()
    except Exception as exc:  # unreadable GeoTIFF keys or WKT: treat as absent, say so
        log.warning("%s: CRS in the header cannot be parsed (%s); treating it as missing", path, _short(exc))
        return None


def resolve_crs(file_crs: pyproj.CRS | None, user_crs: pyproj.CRS | None, path: Path) -> pyproj.CRS:
    """The CRS of a file: its own, or the user's when it has none; an error when neither
    exists or they differ."""
    if file_crs is None and user_crs is None:
        raise CRSError(f"{path}: the file has no CRS; give one with --crs (for example --crs EPSG:7415)")
    if file_crs is None:
        return user_crs
    if user_crs is not None and not same_crs(file_crs, user_crs):
        raise CRSError(
            f"{path}: the file's CRS is {crs_name(file_crs)} but --crs says {crs_name(user_crs)}; "
            "leave out --crs or reproject the file"
        )
    return user_crs if user_crs is not None else file_crs


def same_crs(a: pyproj.CRS, b: pyproj.CRS) -> bool:
    """Same CRS, or the same horizontal CRS when only one of them has a vertical part."""
    if a.equals(b, ignore_axis_order=True):
        return True
    ha = a.sub_crs_list[0] if a.is_compound else a
    hb = b.sub_crs_list[0] if b.is_compound else b
    return ha.equals(hb, ignore_axis_order=True) and (a.is_compound != b.is_compound)


def _short(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:200] if text else type(exc).__name__
