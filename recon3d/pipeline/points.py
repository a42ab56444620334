"""Where a run's points come from: read a tile at a time, never all at once.

A :class:`LasStore` reads LAS/LAZ files once, in chunks, and sorts their points into
square buckets on disk (in the run's work folder), so a tile reads only the buckets it
overlaps. A :class:`MemoryStore` holds a cloud already in memory (a stereo cloud, a
PLY file). Both give every point its place in the survey (``order``: files in the
order of their lower-left corners, then names, points in file order), and the
figures the survey-wide rules need (:class:`CloudSummary`), so that a tile's points
and their order are the same whatever the tiling.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyproj

from recon3d.core.geo import check_area_of_use, crs_name
from recon3d.core.pointcloud import ASPRS, PointCloud, column_bounds
from recon3d.errors import CRSError, InputError
from recon3d.terrain.dsm import SpacingGrid

log = logging.getLogger(__name__)

__all__ = ["GROSS_HEIGHT_ERROR", "CloudSummary", "LasStore", "MemoryStore", "TilePoints", "lexsort_ties"]

#: Metres from the cloud's median height beyond which a point is a gross error
#: (no terrain or building spans 10 km vertically): dropped, with a warning.
GROSS_HEIGHT_ERROR = 1e4

#: Points read from a LAS/LAZ file at a time.
CHUNK = 1_000_000

#: Points a bucket holds about (its side is a power of two metres, 16 to 1024).
BUCKET_POINTS = 250_000

#: File of a bucket folder that says its store is complete (:meth:`LasStore.open`).
STORE_FILE = "store.pickle"


@dataclass
class CloudSummary:
    """What the whole survey says, read once: the survey-wide rules use it, not a tile.

    Attributes
    ----------
    count : int
        Points kept (repeats and gross height errors left out).
    bounds : (2, 3) float
        Lowest and highest corner of the kept points.
    crs : pyproj.CRS
    dtypes : dict of str to numpy dtype
        The per-point attributes every point carries.
    spacing : float
        Mean point spacing (:func:`recon3d.terrain.dsm.point_spacing`'s measure).
    returns : bool
        Some points are echoes of multi-return pulses.
    colour : str or None
        The colour index the points support (see :func:`recon3d.buildings.vegetation.colour_kind`).
    provider_classes : bool
        The provider classified the points (at least 1 % ground, class 2).
    quality_cut : float or None
        Stereo matching score below which a point does not shape the minimum surface.
    median_z : float
        Median height (to the metre), the reference of the gross-error test.
    gross : int
        Points dropped as gross height errors.
    repeats : int
        Points two overlapping tiles both held, kept once.
    ground_points : int
        Points the provider classified ground (2).
    all_observed : bool
        Stereo: every point was matched (none filled in); True for other clouds.
    """

    count: int
    bounds: np.ndarray
    crs: pyproj.CRS | None
    dtypes: dict[str, np.dtype]
    spacing: float
    returns: bool
    colour: str | None
    provider_classes: bool
    quality_cut: float | None = None
    median_z: float = 0.0
    gross: int = 0
    repeats: int = 0
    ground_points: int = 0
    all_observed: bool = True


@dataclass
class TilePoints:
    """The points of one tile's window.

    Attributes
    ----------
    cloud : PointCloud
    order : (n,) int64
        Each point's place in the survey; the points come in that order.
    row, col : (n,) int64
        Each point's cell in the whole DSM grid.
    """

    cloud: PointCloud
    order: np.ndarray
    row: np.ndarray
    col: np.ndarray

    def __len__(self) -> int:
        return len(self.order)

    def inside(self, rows: slice, cols: slice) -> np.ndarray:
        """(n,) bool: the points whose cell lies in ``[rows, cols]`` of the DSM grid."""
        return _in_window(self.row, self.col, rows, cols)

    def subset(self, keep: np.ndarray) -> TilePoints:
        return TilePoints(self.cloud[keep], self.order[keep], self.row[keep], self.col[keep])


def _in_window(row: np.ndarray, col: np.ndarray, rows: slice, cols: slice) -> np.ndarray:
    """(n,) bool: the cells (row, col) inside ``[rows, cols]``."""
    return (row >= rows.start) & (row < rows.stop) & (col >= cols.start) & (col < cols.stop)


def cell_rowcol(xyz: np.ndarray, transform) -> tuple[np.ndarray, np.ndarray]:
    """(n,) int64 row and column of each point's cell in the grid of ``transform``."""
    col = np.floor((xyz[:, 0] - transform.c) / transform.a).astype(np.int64)
    row = np.floor((xyz[:, 1] - transform.f) / transform.e).astype(np.int64)
    return row, col


def _gross(z: np.ndarray, median: float, vertical: float) -> np.ndarray:
    return np.abs(z - median) > GROSS_HEIGHT_ERROR / vertical


@dataclass
class _Part:
    """The summary figures of some of the kept points, merged with ``+`` into the survey's."""

    count: int
    lo: np.ndarray
    hi: np.ndarray
    covered: np.ndarray  # cells of the spacing grid holding points
    ground: int = 0
    returns: bool = False
    nir: bool = False
    rgb: bool = False
    all_observed: bool = True

    @classmethod
    def of(cls, cloud: PointCloud, grid: SpacingGrid) -> _Part:
        xyz, a = cloud.xyz, cloud.attributes
        if not len(cloud):
            return cls(0, np.full(3, np.inf), np.full(3, -np.inf), np.zeros(grid.shape, bool))
        part = cls(len(cloud), *column_bounds(xyz), grid.occupancy(xyz[:, :2]))
        if "classification" in a:
            part.ground = int(np.count_nonzero(a["classification"] == ASPRS.GROUND))
        if "number_of_returns" in a:
            part.returns = bool(np.any(np.asarray(a["number_of_returns"]) > 1))
        if "nir" in a:
            part.nir = bool(np.any(np.asarray(a["nir"]) > 0))
        if "observed" in a:
            part.all_observed = bool(np.all(np.asarray(a["observed"]) > 0))
        if {"red", "green", "blue"} <= set(a):
            part.rgb = bool(np.any(np.asarray(a["red"], np.float64) + np.asarray(a["green"], np.float64)
                                   + np.asarray(a["blue"], np.float64) > 0))
        return part

    def __add__(self, o: _Part) -> _Part:
        return _Part(self.count + o.count, np.minimum(self.lo, o.lo), np.maximum(self.hi, o.hi), self.covered | o.covered,
                     self.ground + o.ground, self.returns or o.returns, self.nir or o.nir, self.rgb or o.rgb,
                     self.all_observed and o.all_observed)


def _summary(parts: list[_Part], grid: SpacingGrid, crs, dtypes: dict, median: float, *,
             quality: np.ndarray | None = None) -> CloudSummary:
    """:class:`CloudSummary` of the kept points, from the figures of their parts."""
    from recon3d.terrain.ground import quality_cut

    p = parts[0]
    for more in parts[1:]:
        p = p + more
    colour = None
    if {"red", "green", "blue"} <= set(dtypes):
        colour = "ndvi" if "nir" in dtypes and p.nir else "exg" if p.rgb else None
    return CloudSummary(
        count=p.count, bounds=np.stack([p.lo, p.hi]), crs=crs, dtypes=dtypes,
        spacing=grid.spacing(p.covered, p.count) if p.count else 0.0, returns=p.returns, colour=colour,
        provider_classes="classification" in dtypes and p.count > 0 and p.ground / p.count >= 0.01,
        quality_cut=quality_cut(quality), median_z=median, ground_points=p.ground, all_observed=p.all_observed,
    )


class MemoryStore:
    """The points of a cloud held in memory (a stereo cloud, a PLY file).

    Parameters
    ----------
    cloud : PointCloud
    vertical : float
        Metres per height unit of the cloud's CRS (for the gross-error test).
    """

    def __init__(self, cloud: PointCloud, *, vertical: float = 1.0) -> None:
        z = cloud.xyz[:, 2]
        median = float(np.median(z)) if len(z) else 0.0
        gross = _gross(z, median, vertical)
        raw_lo, raw_hi = cloud.bounds if len(cloud) else (np.zeros(3), np.zeros(3))
        kept = cloud[~gross] if gross.any() else cloud
        self.cloud = kept
        self.order = np.flatnonzero(~gross) if gross.any() else np.arange(len(cloud))
        dtypes = {k: np.asarray(v).dtype for k, v in cloud.attributes.items()}
        grid = SpacingGrid.over(raw_lo[:2], raw_hi[:2])
        self.summary = _summary([_Part.of(kept, grid)], grid, cloud.crs, dtypes, median,
                                quality=kept.attributes.get("quality"))
        self.summary.gross = int(gross.sum())
        self._cells: tuple | None = None

    def read(self, rows: slice, cols: slice, transform) -> TilePoints:
        """The points whose DSM cell lies in ``[rows, cols]`` of the grid of ``transform``."""
        if self._cells is None or self._cells[0] != transform:
            self._cells = (transform, *cell_rowcol(self.cloud.xyz, transform))
        _, row, col = self._cells
        keep = _in_window(row, col, rows, cols)
        if keep.all():
            return TilePoints(self.cloud, self.order, row, col)
        return TilePoints(self.cloud[keep], self.order[keep], row[keep], col[keep])

    def chunks(self):
        """The kept points, a part at a time (here all at once)."""
        yield self.cloud


@dataclass
class LasFile:
    """One input file, from its header."""

    path: Path
    mins: np.ndarray
    maxs: np.ndarray
    count: int
    point_format: int
    names: list[str]
    crs: pyproj.CRS | None


class LasStore:
    """LAS/LAZ files read once into square buckets on disk, then a tile at a time.

    Parameters
    ----------
    paths : list of Path
        One or many files of one survey (same CRS and point format).
    folder : Path
        Where the buckets are written (the run's work folder); created if needed.
    crs : pyproj.CRS, optional
        For files without one.
    progress : callable, optional
        Called with (points read so far, points in all).

    Raises
    ------
    InputError
        A file missing, damaged or empty (named), tiles of different point formats, a
        tile given twice.
    CRSError
        No CRS and none given, a conflicting one, or tiles in different CRSs.
    """

    def __init__(self, paths: list[Path], folder: Path, *, crs: pyproj.CRS | None = None,
                 progress: Callable[[int, int], None] | None = None, executor=None) -> None:
        from recon3d.io import las as las_io
        from recon3d.pipeline.executor import Executor

        executor = executor or Executor(1)
        self.folder = Path(folder)
        files = [_header(Path(p), crs) for p in paths]
        files.sort(key=lambda f: (tuple(np.round(f.mins[:2], 3)), str(f.path)))
        _check_survey(files)
        self.files = files
        self.crs = files[0].crs
        names = [n for n in las_io.KEPT_DIMENSIONS if all(n in f.names for f in files)]
        total = sum(f.count for f in files)
        lo = np.min([f.mins for f in files], axis=0)
        hi = np.max([f.maxs for f in files], axis=0)
        density = total / max(float(np.prod(hi[:2] - lo[:2])), 1.0)
        self.bucket = float(2 ** int(np.clip(round(math.log2(math.sqrt(BUCKET_POINTS / max(density, 1e-9)))), 4, 10)))
        self.folder.mkdir(parents=True, exist_ok=True)
        self.dtype = _record_dtype(files[0].path, names)
        bases = np.cumsum([0] + [f.count for f in files[:-1]])
        jobs = [(f.path, i, int(base), names, self.dtype, self.bucket, self.folder)
                for i, (f, base) in enumerate(zip(files, bases, strict=True))]
        done = (lambda k: progress(int(bases[k - 1] + files[k - 1].count), total)) if progress else None
        read = executor.map(_bucket_file, jobs, done=done)
        raw_lo = np.min([r[0] for r in read], axis=0)
        raw_hi = np.max([r[1] for r in read], axis=0)
        heights: dict[int, int] = {}
        for _, _, counts in read:
            for k, c in counts.items():
                heights[k] = heights.get(k, 0) + c
        median = _histogram_median(heights)
        vertical = _vertical(self.crs)
        grid = SpacingGrid.over(raw_lo[:2], raw_hi[:2])
        buckets = sorted({p.name.split(".")[0] for p in self.folder.glob("*.part*.bin")})
        cleaned = executor.map(_clean_bucket, [(self.folder, b, self.dtype, median, vertical, len(files) > 1, grid)
                                               for b in buckets])
        self.summary = _summary([c[0] for c in cleaned], grid, self.crs, {n: self.dtype[n] for n in names}, median)
        self.summary.gross = sum(c[1] for c in cleaned)
        self.summary.repeats = sum(c[2] for c in cleaned)

    @classmethod
    def open(cls, paths: list[Path], folder: Path, *, crs: pyproj.CRS | None = None,
             progress: Callable[[int, int], None] | None = None, executor=None) -> LasStore:
        """The store kept in ``folder`` by an earlier run (a resumed one), else a new one
        (whatever a killed run left half written there is removed first)."""
        import pickle
        import shutil

        folder = Path(folder)
        kept = folder / STORE_FILE
        if kept.is_file():
            with open(kept, "rb") as f:
                store = pickle.load(f)
            store.folder = folder  # the work folder moves to the resumed run's
            return store
        shutil.rmtree(folder, ignore_errors=True)
        store = cls(paths, folder, crs=crs, progress=progress, executor=executor)
        tmp = folder / f".{STORE_FILE}"
        with open(tmp, "wb") as f:
            pickle.dump(store, f)
        tmp.rename(kept)
        return store

    def _path(self, bx: int, by: int) -> Path:
        return self.folder / f"{bx}_{by}.bin"

    def _buckets(self) -> list[Path]:
        return sorted(self.folder.glob("*_*.bin"))

    def _load(self, path: Path) -> np.ndarray:
        return np.fromfile(path, dtype=self.dtype)

    def chunks(self):
        """The kept points, a bucket at a time."""
        for path in self._buckets():
            yield self._cloud(self._load(path))

    def _cloud(self, rec: np.ndarray) -> PointCloud:
        xyz = np.column_stack([rec["x"], rec["y"], rec["z"]])
        names = [n for n in self.dtype.names if n not in ("x", "y", "z", "order")]
        return PointCloud(xyz, {n: np.ascontiguousarray(rec[n]) for n in names}, self.crs)

    # ------------------------------------------------------------------ reading tiles

    def read(self, rows: slice, cols: slice, transform) -> TilePoints:
        """The points whose DSM cell lies in ``[rows, cols]`` of the grid of ``transform``, in survey order."""
        x0 = transform.c + cols.start * transform.a
        x1 = transform.c + cols.stop * transform.a
        y1 = transform.f + rows.start * transform.e
        y0 = transform.f + rows.stop * transform.e
        b = self.bucket
        picked, rows_in, cols_in = [], [], []  # only the window's records of each bucket are kept
        for bx in range(math.floor(x0 / b) - 1, math.floor(x1 / b) + 1):
            for by in range(math.floor(y0 / b) - 1, math.floor(y1 / b) + 1):
                path = self._path(bx, by)
                if path.exists():
                    rec = self._load(path)
                    row, col = cell_rowcol(_xy(rec), transform)
                    inside = _in_window(row, col, rows, cols)
                    if inside.any():
                        picked.append(rec[inside])
                        rows_in.append(row[inside])
                        cols_in.append(col[inside])
                    del rec, row, col, inside
        if not picked:
            none = np.zeros(0, self.dtype)
            return TilePoints(self._cloud(none), *(np.zeros(0, np.int64) for _ in range(3)))
        # one gather per field, straight into survey order
        order = np.concatenate([r["order"] for r in picked])
        sort = np.argsort(order, kind="stable")

        def field(name: str) -> np.ndarray:
            return np.concatenate([r[name] for r in picked])[sort]

        xyz = np.empty((len(sort), 3))
        for axis, name in enumerate("xyz"):
            xyz[:, axis] = field(name)
        names = [n for n in self.dtype.names if n not in ("x", "y", "z", "order")]
        cloud = PointCloud(xyz, {n: field(n) for n in names}, self.crs)
        return TilePoints(cloud, order[sort], np.concatenate(rows_in)[sort], np.concatenate(cols_in)[sort])


def _xy(rec: np.ndarray) -> np.ndarray:
    """(n, 2) float64 view of the x and y of bucket records (their first two fields)."""
    return np.ndarray((len(rec), 2), np.float64, rec, 0, (rec.itemsize, 8))


def _record_dtype(path: Path, names: list[str]) -> np.dtype:
    """The bucket record of a survey: coordinates, survey order and the kept attributes
    with the dtypes laspy reads them in (the first point of ``path`` tells)."""
    import laspy

    try:
        with laspy.open(path) as reader:
            chunk = next(reader.chunk_iterator(1))
    except Exception as exc:  # laspy and lazrs raise many kinds on a damaged file
        raise InputError(f"{path}: cannot read LAS/LAZ ({_short(exc)})") from None
    return np.dtype([("x", "f8"), ("y", "f8"), ("z", "f8"), ("order", "i8")]
                    + [(n, np.asarray(chunk[n]).dtype) for n in names])


def _bucket_file(job: tuple) -> tuple[np.ndarray, np.ndarray, dict[int, int]]:
    """Read one input file in chunks into its own part of every bucket it touches (a
    worker's job: files are read in parallel); its raw bounds and its points per metre of height."""
    import laspy

    from recon3d.io.las import scaling_is_finite

    path, index, base, names, dtype, bucket, folder = job
    heights: dict[int, int] = {}
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    read = 0
    try:
        with laspy.open(path) as reader:
            finite = scaling_is_finite(reader.header)
            for chunk in reader.chunk_iterator(CHUNK):
                xyz = np.column_stack([chunk.x, chunk.y, chunk.z]).astype(np.float64, copy=False)
                if not finite and not np.isfinite(xyz).all():
                    raise InputError(f"{path}: {int((~np.isfinite(xyz)).any(axis=1).sum())} points "
                                     "have NaN or infinite coordinates")
                rec = np.empty(len(xyz), dtype)
                rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
                rec["order"] = np.arange(base + read, base + read + len(xyz), dtype=np.int64)
                for n in names:
                    rec[n] = np.asarray(chunk[n])
                _append(rec, bucket, folder, index)
                chunk_lo, chunk_hi = column_bounds(xyz)
                lo, hi = np.minimum(lo, chunk_lo), np.maximum(hi, chunk_hi)
                keys, counts = _metre_counts(xyz[:, 2])
                for k, c in zip(keys.tolist(), counts.tolist(), strict=True):
                    heights[k] = heights.get(k, 0) + c
                read += len(xyz)
    except InputError:
        raise
    except Exception as exc:  # laspy and lazrs raise many kinds on a damaged file
        raise InputError(f"{path}: cannot read LAS/LAZ ({_short(exc)})") from None
    if read == 0:
        raise InputError(f"{path}: the point cloud is empty (0 points)")
    return lo, hi, heights


def _metre_counts(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The whole metres the heights ``z`` (n,) fall in, ascending, and the points in each:
    ``np.unique(np.floor(z), return_counts=True)``, counted instead of sorted where the
    heights span fewer metres than there are points (a gross error makes it sort)."""
    metre = np.floor(z).astype(np.int64)
    low = int(metre.min())
    span = int(metre.max()) - low + 1
    if span > len(metre):
        return np.unique(metre, return_counts=True)
    counts = np.bincount(metre - low, minlength=span)
    keys = np.flatnonzero(counts)
    return keys + low, counts[keys]


def _append(rec: np.ndarray, bucket: float, folder: Path, index: int) -> None:
    """Append records to the part of file ``index`` of each bucket they fall in."""
    bx = np.floor(rec["x"] / bucket).astype(np.int64)
    by = np.floor(rec["y"] / bucket).astype(np.int64)
    x0, y0 = int(bx.min()), int(by.min())
    key = (bx - x0) * (int(by.max()) - y0 + 1) + (by - y0)  # one integer per bucket: a 1-d sort
    if key.max() < 1 << 16:  # a chunk spans few buckets: numpy's stable sort of 16-bit keys is a radix sort
        key = key.astype(np.uint16)
    sort = np.argsort(key, kind="stable")
    key = key[sort]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    for start, stop in zip(starts, [*starts[1:], len(key)], strict=True):
        i = sort[start]
        with open(folder / f"{bx[i]}_{by[i]}.part{index:06d}.bin", "ab") as f:
            rec[sort[start:stop]].tofile(f)


def _clean_bucket(job: tuple) -> tuple[_Part, int, int]:
    """Join a bucket's parts (file by file: the survey's order), drop gross height errors
    and, for several files, the repeats of overlapping tiles (identical points share a
    bucket); its summary figures, gross errors and repeats."""
    folder, name, dtype, median, vertical, dedupe, grid = job
    parts = sorted(folder.glob(f"{name}.part*.bin"))
    rec = np.concatenate([np.fromfile(p, dtype=dtype) for p in parts])
    keep = ~_gross(rec["z"], median, vertical)
    gross = int((~keep).sum())
    repeats = 0
    if dedupe:
        first = _first_of_each(rec)
        repeats = int((keep & ~first).sum())
        keep &= first
    rec = rec[keep]
    rec.tofile(folder / f"{name}.bin")
    for p in parts:
        p.unlink()
    xyz = np.column_stack([rec["x"], rec["y"], rec["z"]])
    names = [n for n in dtype.names if n not in ("x", "y", "z", "order")]
    return _Part.of(PointCloud(xyz, {n: rec[n] for n in names}), grid), gross, repeats


def _first_of_each(rec: np.ndarray) -> np.ndarray:
    """(n,) bool: every record but the repeats (same x, y, z and GPS time) of one earlier in the survey."""
    keys = [rec["x"], rec["y"], rec["z"]]
    if "gps_time" in rec.dtype.names:
        keys.append(rec["gps_time"])
    # sorted on one code that identical points share (a third of the time of sorting on x,
    # y and z), and where codes tie on x, y, z, time and survey order: repeats stand next
    # to the first of them, whatever points a code happens to join
    code = _point_code(keys)
    order = lexsort_ties([rec["order"], *keys[::-1], code], 1)
    # only neighbours with one code can be repeats: their keys alone are compared (most
    # surveys have none; gathering every key in sorted order took half the time)
    code = code[order]
    tie = np.flatnonzero(code[1:] == code[:-1])
    earlier, later = order[tie], order[tie + 1]
    same = np.ones(len(tie), bool)
    for key in keys:
        same &= key[earlier] == key[later]
    repeat = np.zeros(len(rec), bool)
    repeat[later[same]] = True
    return ~repeat


def _point_code(keys: list[np.ndarray]) -> np.ndarray:
    """(n,) uint64 mix of the bits of the (n,) float keys: equal for points whose keys are
    all equal (0.0 and -0.0 alike), rarely equal for others."""
    code = np.zeros(len(keys[0]), np.uint64)
    for key in keys:
        code ^= (np.asarray(key, np.float64) + 0.0).view(np.uint64)  # + 0.0: -0.0 becomes 0.0
        code *= np.uint64(0x9E3779B97F4A7C15)  # wraps modulo 2^64
        code ^= code >> np.uint64(29)
    return code


def lexsort_ties(keys: list[np.ndarray], decisive: int) -> np.ndarray:
    """``np.lexsort(keys)`` (the last key first), sorted on the last ``decisive`` keys and
    on the others only where those tie.

    Points rarely share their first coordinates, so most of them are sorted on the
    deciding keys alone (about half the time of a six-key sort). The keys that decide
    must hold no NaN (with one, this is np.lexsort itself).
    """
    if any(key.dtype.kind == "f" and np.isnan(key).any() for key in keys[-decisive:]):
        return np.lexsort(keys)
    order = np.lexsort(keys[-decisive:])
    rest = keys[:-decisive]
    if not rest or len(order) < 2:
        return order
    same = np.ones(len(order) - 1, bool)
    for key in keys[-decisive:]:
        k = key[order]
        same &= k[1:] == k[:-1]
    if not same.any():
        return order
    tied = np.flatnonzero(np.r_[same, False] | np.r_[False, same])
    group = np.cumsum(np.r_[True, ~same])[tied]
    members = order[tied]  # each group in input order, as the stable sort left it
    order[tied] = members[np.lexsort([*(key[members] for key in rest), group])]
    return order


def _histogram_median(heights: dict[int, int]) -> float:
    """The median height to the metre, from counts of points per whole metre."""
    if not heights:
        return 0.0
    keys = np.array(sorted(heights))
    counts = np.array([heights[k] for k in keys])
    half = (counts.sum() + 1) // 2
    return float(keys[np.searchsorted(np.cumsum(counts), half)]) + 0.5


def _vertical(crs) -> float:
    from recon3d.core.geo import crs_units

    try:
        return crs_units(crs).vertical
    except Exception:  # crs_units reports a bad CRS later, with the file's name
        return 1.0


def _header(path: Path, crs: pyproj.CRS | None) -> LasFile:
    """The header of one input file, checked."""
    import laspy

    from recon3d.io import las as las_io
    from recon3d.io import require_file

    path = require_file(path, "point cloud")
    las_io.check_header(path)
    try:
        with laspy.open(path) as reader:
            h = reader.header
            try:
                file_crs = h.parse_crs()
            except Exception as exc:
                log.warning("%s: CRS in the header cannot be parsed (%s); treating it as missing", path, _short(exc))
                file_crs = None
            info = LasFile(path, np.asarray(h.mins, np.float64), np.asarray(h.maxs, np.float64), int(h.point_count),
                           int(h.point_format.id), list(h.point_format.dimension_names), None)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{path}: cannot read LAS/LAZ header ({_short(exc)})") from None
    if info.count == 0:
        raise InputError(f"{path}: the point cloud is empty (0 points)")
    info.crs = las_io.resolve_crs(file_crs, crs, path)
    check_area_of_use(info.crs, info.mins, info.maxs, source=str(path))
    return info


def _check_survey(files: list[LasFile]) -> None:
    """Tiles of one survey: one point format, one CRS, no tile given twice."""
    from recon3d.io.las import same_crs

    first = files[0]
    seen: dict = {}
    for f in files:
        if f.point_format != first.point_format:
            raise InputError(f"{f.path}: point format {f.point_format}, but {first.path.name} has "
                             f"{first.point_format}; tiles of one survey share their point format")
        if not same_crs(f.crs, first.crs):
            raise CRSError(f"{f.path}: CRS {crs_name(f.crs)}, but {first.path.name} is in {crs_name(first.crs)}; "
                           "reproject the tiles to one CRS")
        key = (tuple(np.round(f.mins, 3)), tuple(np.round(f.maxs, 3)), f.count)
        if key in seen:
            raise InputError(f"{f.path}: the same tile as {seen[key].name} (same bounds and point count); give it once")
        seen[key] = f.path


def _short(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:200] if text else type(exc).__name__
