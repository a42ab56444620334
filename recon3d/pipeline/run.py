"""``recon3d run``: the stage table, the tiles, the output folder and run.json.

This is the only package that knows file names, the order of stages, the tiles and
the output folder. A run reads its points into a store that gives them a tile at a
time (:mod:`recon3d.pipeline.points`), cuts the area into work tiles
(:mod:`recon3d.pipeline.tiling`), and alternates two kinds of work: passes over the
tiles, which turn each tile's points into rasters and per-point values
(:mod:`recon3d.pipeline.passes`, on worker processes or a Dask cluster), and the
stages between them, which work on the whole grid (hole filling, the ground filter's
terrain, the DTM, building detection) or on whole buildings (their solids). Each
stage fills in one typed result of the :class:`Run`. Every per-point rule reads the
same neighbourhood in a tile as in the whole survey, and the survey-wide figures are
summed over the tiles, so the products are the same bytes whatever the tiling and the
number of workers.

The whole output folder is written under a temporary name beside the target and
renamed at the end, so a failed run leaves nothing behind and an existing folder is
replaced only with ``overwrite=True``.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyproj

from recon3d import __version__
from recon3d.buildings import align, blocks, detect, lod, vegetation
from recon3d.buildings.measure import measure_heights
from recon3d.config import PipelineConfig
from recon3d.core.accuracy import AccuracyReport
from recon3d.core.city import Building, CityModel
from recon3d.core.geo import LocalFrame, crs_units
from recon3d.core.dates import today
from recon3d.core.memory import available_memory, require_memory
from recon3d.core.pointcloud import PointCloud
from recon3d.core.raster import Raster, grid_for_bounds
from recon3d.errors import InputError
from recon3d.io.las import las_tiles
from recon3d.pipeline import inputs as inputs_mod
from recon3d.pipeline import output, passes
from recon3d.pipeline.executor import Executor, connect, default_workers, release_memory
from recon3d.pipeline.inputs import Inputs, Source
from recon3d.pipeline.points import MemoryStore, cell_rowcol
from recon3d.pipeline.spill import Spill
from recon3d.pipeline.tiling import BLOCK, Tile, plan_tiles
from recon3d.terrain import dsm as dsm_stage
from recon3d.terrain import dtm as dtm_stage
from recon3d.terrain import ground as ground_stage

log = logging.getLogger(__name__)

__all__ = ["STAGES", "Run", "RunResult", "run"]

ProgressCallback = Callable[[str, int, int], None]


# --------------------------------------------------------------------------- typed stage results


@dataclass
class Grid:
    """The product grid and its work tiles.

    Attributes
    ----------
    transform : Affine
    shape : (rows, cols)
    tiles : list of Tile
        In Morton order.
    spec : passes.Spec
        What every tile job shares.
    buffers : dict of str to int
        Cells of points each pass reads around a tile's core.
    points : list of int
        Points in each tile's core: the passes hand out the largest tiles first.
    """

    transform: Any
    shape: tuple[int, int]
    tiles: list[Tile]
    spec: passes.Spec
    buffers: dict[str, int]
    points: list[int]

    def raster(self, data: np.ndarray, crs, **tags: str) -> Raster:
        return Raster(data, self.transform, crs, dict(tags))

    def place(self, paths: list[Path], key: str, dtype=np.float64, fill=np.nan, factor: int = 1) -> np.ndarray:
        """The whole grid of one raster result of a tile pass, each tile's core in its
        place; on a grid ``factor`` times finer than the DSM's with ``factor``."""
        return self.mosaic(paths, key, dtype, fill, factor)[:, :]

    def mosaic(self, paths: list[Path], key: str, dtype=np.float64, fill=np.nan, factor: int = 1) -> TileMosaic:
        """One raster result of a tile pass, read a window at a time (see :class:`TileMosaic`)."""
        return TileMosaic(self, paths, key, np.dtype(dtype), fill, factor)


@dataclass
class TileMosaic:
    """One raster result of a tile pass, read from the tiles' saved results a window at
    a time: a stage that walks the grid in strips holds one strip, not the survey.

    Indexing with two slices, ``mosaic[rows, cols]``, returns that window as a new
    array, each tile's core in its place and ``fill`` where no tile is.
    """

    grid: Grid
    paths: list[Path]
    key: str
    dtype: np.dtype
    fill: Any
    factor: int = 1

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.shape[0] * self.factor, self.grid.shape[1] * self.factor

    def __getitem__(self, window: tuple[slice, slice]) -> np.ndarray:
        (r0, r1, _), (c0, c1, _) = (w.indices(n) for w, n in zip(window, self.shape, strict=True))
        out = np.full((max(r1 - r0, 0), max(c1 - c0, 0)), self.fill, self.dtype)
        f = self.factor
        for tile, path in zip(self.grid.tiles, self.paths, strict=True):
            tr, tc = tile.rows.start * f, tile.cols.start * f
            a0, a1 = max(r0, tr), min(r1, tile.rows.stop * f)
            b0, b1 = max(c0, tc), min(c1, tile.cols.stop * f)
            if a0 < a1 and b0 < b1:
                with np.load(path) as data:
                    out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = data[self.key][a0 - tr:a1 - tr, b0 - tc:b1 - tc]
        return out


@dataclass
class Surface:
    """The DSM and what is known of its cells."""

    dsm: Raster
    filled: np.ndarray  # cells holding no point at all, filled from their rim
    unobserved: np.ndarray | None = None  # stereo: cells holding no observed point
    consistent: np.ndarray | None = None  # stereo: cells holding a guess with evidence (images agree, or foreground)
    common_area: np.ndarray | None = None  # stereo: cells both images of a matched pair see
    first_returns: int = 0
    surface_bounds: tuple[np.ndarray, np.ndarray] | None = None  # first returns, not noise
    ground_surface: tuple | None = None  # lowest trusted point per cell of the ground filter's grid, its transform
    upper_median: np.ndarray | None = None  # frame stereo: the upper median of each pair's points per cell, until used
    foreground: np.ndarray | None = None  # frame stereo: cells holding a guess filled beyond an occlusion's width

    @property
    def matched(self) -> np.ndarray:
        """(rows, cols) bool: cells holding a matched (observed) point."""
        cells = np.isfinite(self.dsm.data) & ~self.filled
        return cells if self.unobserved is None else cells & ~self.unobserved


@dataclass
class Terrain:
    """The ground filter's result and the terrain products."""

    dtm: Raster
    ndsm: Raster
    noise: float  # height noise of the minimum surface (CRS units, as run.json records it)
    sunk: np.ndarray | None = None  # (rows, cols) bool: DTM cells interpolated again under the ground tie points


@dataclass
class Evidence:
    """What the points say of the cells, for the building detection."""

    share: np.ndarray  # share of vegetation among each cell's upper points
    planar: np.ndarray | None  # share of each cell's upper points on a local plane, until the detection
    fine: detect.FineSurface | None  # the detection's alone, read from the tiles a strip at a time
    plane_tolerance: float
    density: float  # first returns per square metre
    crowns: np.ndarray | None = None  # cells of detected blobs found to be tree crowns after roof modelling

    @property
    def vegetated(self) -> np.ndarray:
        """(rows, cols) bool: cells whose upper points are mostly vegetation."""
        return detect.vegetation_mask(self.share)


@dataclass
class Quality:
    """The accuracy report's figures (report.json) and the model's rasters."""

    model_dsm: Raster | None = None
    roof_cover: np.ndarray | None = None
    model_top: float = 0.0  # where the rays over the model start (ray_top)
    model_scan: Raster | None = None  # the model scanned at the points, gridded like the DSM
    ortho: Any = None
    ortho_diff: Raster | None = None
    textured: Any = None  # the model textured from the images (recon3d.stereo.texture)
    changes: Any = None


@dataclass
class Run:
    """One run: what it was given, what it chose and noticed, and each stage's result."""

    inputs: Inputs
    config: PipelineConfig
    out_dir: Path
    work_dir: Path
    cache: Path
    executor: Executor
    workers: int | None
    date: str  # the products' date when the input holds none: the day the run started
    grids: Spill  # maps the whole-area grids from the work folder once the buildings are found
    progress: Callable[[str], None] | None = None
    keep_points: bool | None = None
    source: Source = field(default_factory=Source)
    grid: Grid | None = None
    surface: Surface | None = None
    terrain: Terrain | None = None
    evidence: Evidence | None = None
    city: CityModel | None = None
    labels: np.ndarray | None = None
    quality: Quality = field(default_factory=Quality)
    passes: dict[str, list[Path]] = field(default_factory=dict)  # each tile pass's saved results
    auto: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    report: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)

    def warn(self, message: str) -> None:
        """A warning the user must see: logged (the terminal), kept for run.json and the report."""
        log.warning("%s", message)
        self.warnings.append(message)

    @property
    def units(self):
        return self.source.units

    @property
    def stereo(self) -> str | None:
        """None for a point cloud, "frame" or "satellite" for stereo inputs."""
        if self.source.scene is None:
            return None
        return "satellite" if self.inputs.satellite_paths is not None else "frame"

    def tiles(self, name: str, func: Callable, args: list[tuple]) -> list[Path]:
        """Run one pass over every tile (see :meth:`Executor.tiles`).

        The memory this process freed goes back to the system first, and the pages of
        the mapped grids it reads to send the tiles their windows go back after each
        tile: the workers need the memory more."""
        release_memory()
        self.grids.release()
        g = self.grid
        local = isinstance(g.spec.store, MemoryStore) or len(g.tiles) == 1

        def progress(message: str) -> None:
            self.grids.release()
            if self.progress is not None:
                self.progress(message)

        return self.executor.tiles(name, func, g.spec, g.tiles, args, progress=progress, local=local,
                                   sizes=g.points)


@dataclass
class RunResult:
    """What :func:`run` returns: the products in memory and the run's record.

    The per-point arrays (``cloud``, ``is_ground``, ``vegetation``, ``point_classes``,
    ``reference_classes``, ``roughness``) are filled only with ``keep_points=True``
    (they hold the whole cloud in memory), in the survey's order.
    """

    out_dir: Path
    input_path: Path
    config: PipelineConfig
    units: Any
    city: CityModel
    dsm: Raster
    dtm: Raster
    ndsm: Raster
    model_dsm: Raster
    roof_cover: np.ndarray
    model_scan: Raster
    labels: np.ndarray
    auto: dict
    report: dict
    notes: list[str]
    warnings: list[str]
    timings: dict[str, float]
    scene: Any = None
    ortho: Any = None
    ortho_diff: Raster | None = None
    changes: Any = None
    dsm_filled: np.ndarray | None = None
    dsm_unobserved: np.ndarray | None = None
    common_area: np.ndarray | None = None
    vegetation_share: np.ndarray | None = None
    footprints: list | None = None
    cloud: PointCloud | None = None
    is_ground: np.ndarray | None = None
    vegetation: np.ndarray | None = None
    roughness: np.ndarray | None = None
    point_classes: np.ndarray | None = None
    reference_classes: np.ndarray | None = None


# --------------------------------------------------------------------------- the run


def run(
    input_path: str | Path | tuple,
    out_dir: str | Path,
    *,
    crs: pyproj.CRS | None = None,
    footprints: str | Path | None = None,
    checkpoints: str | Path | None = None,
    breaklines: str | Path | None = None,
    altimetry: str | Path | None = None,
    dem: str | Path | None = None,
    truth_dsm: str | Path | None = None,
    old_buildings: str | Path | None = None,
    gcps: str | Path | None = None,
    config: PipelineConfig | None = None,
    overwrite: bool = False,
    workers: int | None = 1,
    progress: ProgressCallback | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    keep_points: bool | None = None,
) -> RunResult:
    """Run the pipeline and write the output folder.

    Parameters
    ----------
    input_path : path-like or sequence of path-likes
        LAS/LAZ or PLY point cloud, LAS/LAZ tiles of one survey (files, a folder of
        them or a glob pattern), a frame-stereo scene folder, or two GeoTIFFs with RPCs
        (satellite stereo).
    out_dir : path-like
        Output folder (see DESIGN.md for its contract).
    crs : pyproj.CRS, optional
        CRS of an input that carries none.
    footprints, checkpoints : path-like, optional
        Building outlines to use instead of detection; reference heights to check against.
    breaklines, altimetry : path-like, optional
        3-D lines (roads, water edges) and spot heights (vector file, or CSV x,y,z for
        altimetry) the DTM must honour; frame stereo also matches within them.
    dem : path-like, optional
        An elevation model (GeoTIFF) that bounds the heights frame stereo or a satellite pair searches.
    truth_dsm : path-like, optional
        A reference DSM (GeoTIFF) the DSM is compared with cell by cell.
    gcps : path-like, optional
        Ground control points (CSV x,y,z in the output CRS) removing the absolute bias
        of a satellite pair's RPCs.
    old_buildings : path-like, optional
        An older building database (footprints or CityJSON) to detect changes against;
        writes changes.geojson, changes.tif and buildings_updated.city.json.
    config : PipelineConfig, optional
    overwrite : bool
        Replace an existing, non-empty ``out_dir``.
    workers : int or None
        Processes for the tiles and the buildings' solids; None uses every CPU this
        process may use where there is work for them (the CLI's default). The output
        does not depend on it. With more than one, the worker processes import the
        calling script again, as ``multiprocessing`` does: its top-level code must sit
        under ``if __name__ == "__main__":``.
    progress : callable, optional
        Called as ``progress(stage_name, index, total)`` before each stage, and with
        ``stage_name`` followed by a detail (``"lod 40/133 buildings"``, ``"dsm surface
        tile 3/16, ETA 40 s"``) during long stages.
    scheduler : str, optional
        Run the tiles and buildings on Dask: a scheduler address (``tcp://host:8786``),
        or ``"local"`` for a LocalCluster of this machine. The work folder must be on a
        file system every worker sees.
    resume : bool
        Take up the work of an earlier run of the same inputs and settings into the same
        ``out_dir`` that was killed or failed: finished tiles are not done again. A run
        with ``resume`` keeps its work when it fails, for the next ``resume``.
    keep_points : bool, optional
        Also return the per-point arrays (the whole cloud in memory); by default when the
        survey has at most :data:`KEEP_POINTS` points.

    Raises
    ------
    InputError
        Bad input or an existing output folder; nothing is written then.
    """
    inputs = _inputs(input_path, crs=crs, footprints=footprints, checkpoints=checkpoints, breaklines=breaklines,
                     altimetry=altimetry, dem=dem, truth_dsm=truth_dsm, old_buildings=old_buildings, gcps=gcps)
    config = config or PipelineConfig()
    out = output.check_output(Path(out_dir), inputs.given(), overwrite=overwrite)
    fingerprint = _fingerprint(inputs, config)
    client = connect(scheduler) if scheduler else None  # a scheduler that does not answer stops the run here
    created = [p for p in (out.parent, *out.parent.parents) if not p.exists()]  # deepest first
    work_dir = output.work_folder(out)
    cache = work_dir / output.WORK_CACHE
    try:
        adopted = resume and output.adopt(out, fingerprint, cache)
    except BaseException:
        shutil.rmtree(work_dir, ignore_errors=True)
        if client is not None:
            _close(client)
        raise
    notes = output.remove_stale(out)
    if adopted:
        notes.append(f"--resume: took up the work of an earlier run ({output.count_results(cache)} tile results)")
    else:
        cache.mkdir()
        if resume:
            notes.append("--resume: no earlier work of this run was found; started afresh")
    (cache / output.FINGERPRINT).write_text(json.dumps(fingerprint, sort_keys=True), encoding="utf-8")
    started = cache / "started"  # a resumed run keeps the day of the run it takes up
    date = started.read_text(encoding="utf-8") if adopted and started.is_file() else today()
    started.write_text(date, encoding="utf-8")
    r = Run(inputs, config, out, work_dir, cache, Executor(default_workers() if workers is None else workers, client),
            workers, keep_points=keep_points, date=date, grids=Spill(cache / "grids"))
    r.notes += notes
    if client is not None:
        r.auto["executor"] = {"value": f"dask {scheduler}", "reason": "--scheduler/--dask"}
    failed = True
    try:
        for index, (name, stage) in enumerate(STAGES):
            if progress:
                progress(name, index, len(STAGES))
                r.progress = lambda detail, n=name, i=index: progress(f"{n} {detail}", i, len(STAGES))
            start = time.perf_counter()
            stage(r)
            release_memory()
            r.grids.release()
            r.timings[name] = round(time.perf_counter() - start, 3)
            log.info("stage %s done in %.2f s", name, r.timings[name])
        result = _result(r)
        shutil.rmtree(cache, ignore_errors=True)
        from recon3d.pipeline.products import run_record, write_json

        write_json(work_dir / output.Products.RUN, run_record(r))
        from recon3d.report import write_report

        write_report(work_dir)
        output.publish(work_dir, out)
        failed = False
    finally:
        r.executor.close()
        if client is not None:
            _close(client)
        if failed and resume:
            log.warning("the work done is kept in %s: run again with --resume to take it up", work_dir)
        elif failed:
            shutil.rmtree(work_dir, ignore_errors=True)  # before its parents can go
            for folder in created:  # a failed run leaves nothing, not even the folders it made
                try:
                    folder.rmdir()
                except OSError:
                    break
        else:
            shutil.rmtree(work_dir, ignore_errors=True)
    return result


def _inputs(input_path, **given) -> Inputs:
    """The inputs named, sorted out: LAS/LAZ tiles, one input, or a satellite pair."""
    items = list(input_path) if isinstance(input_path, tuple | list) else [input_path]
    tiles = las_tiles(items)
    pair = None
    if tiles is not None:
        main = tiles[0]
        tiles = tiles if len(tiles) > 1 else None
    elif len(items) == 1:
        main = items[0]
    elif len(items) == 2:
        pair = tuple(Path(p) for p in items)
        main = pair[0]
    else:
        raise InputError(f"expected one input, LAS/LAZ tiles or two satellite images, got {len(items)} inputs")
    return Inputs(Path(main), tiles, pair, given.pop("crs"), **{k: Path(v) if v else None for k, v in given.items()})


def _fingerprint(inputs: Inputs, config: PipelineConfig) -> dict:
    """What a resumed run must share with the run whose work it takes up."""
    def stat(path: Path) -> list:
        p = Path(path).resolve()
        st = p.stat() if p.exists() else None
        return [str(p), st.st_size if st else None, st.st_mtime_ns if st else None]

    return {"recon3d": __version__, "inputs": [stat(p) for p in inputs.given()],
            "crs": inputs.crs.to_wkt() if inputs.crs is not None else None, "config": config.to_dict()}


def _close(client) -> None:
    cluster = getattr(client, "cluster", None)
    client.close()
    if cluster is not None:
        cluster.close()


# --------------------------------------------------------------------------- stages


def read_inputs(r: Run) -> None:
    """Read and check every input before anything is computed: the points (into the
    store), or a stereo scene's model and images (matched by the next stage)."""
    kind = r.inputs.kind
    if r.inputs.dem and kind == "points":
        raise InputError(f"{r.inputs.dem}: --dem bounds the matching of a stereo input; "
                         f"{r.inputs.input_path} is not one")
    if kind != "points":
        inputs_mod.read_scene(r.inputs, r.source, r.notes)
        return
    r.source = inputs_mod.read_points(r.inputs, r.cache / "points", auto=r.auto, progress=r.progress,
                                      executor=r.executor)
    _points_read(r)


def match_stereo(r: Run) -> None:
    """Dense matching of a scene folder or an RPC pair into the point cloud (nothing to do for clouds)."""
    if r.stereo is None:
        return
    if r.stereo == "satellite":
        cloud = inputs_mod.match_satellite(r.inputs, r.source, r.config, warn=r.warn, progress=r.progress)
    else:
        cloud = inputs_mod.match_frame(r.source, r.config, warn=r.warn, progress=r.progress)
    r.auto["stereo"] = r.source.stereo
    r.source.store = MemoryStore(cloud, vertical=crs_units(cloud.crs, source=str(r.inputs.input_path)).vertical)
    _points_read(r)


def _points_read(r: Run) -> None:
    """The points' CRS, units and sanity; then the vectors, in their CRS."""
    s = r.source
    vectors_read = s.scene is not None and r.stereo == "frame"  # read before matching, which uses them
    inputs_mod.check_points(s, r.inputs, r.warn)
    if not vectors_read:
        inputs_mod.read_vectors(r.inputs, s, s.crs, (s.summary.bounds[0], s.summary.bounds[1]), r.notes)


#: Largest DSM hole filled (m2) when ``dsm.max_hole_area`` is unset, by source, and the reason run.json records.
HOLE_AREA = {
    "frame": (1000.0, "frame stereo: ground hidden behind buildings from one image (a wide-base survey "
                      "hides whole streets), inside the area both images see, filled from the low side of its rim"),
    "satellite": (200.0, "satellite stereo: ground hidden behind buildings, filled from the low side of its rim"),
    "lidar": (25.0, "LiDAR: gaps between scan lines, filled from the mean of their rim"),
}

#: Bytes per DSM cell the raster stages hold at their peak (DSM, DTM, nDSM, masks,
#: filters' working copies, the fine grid of the outlines: about twenty float64 grids).
GRID_BYTES_PER_CELL = 160

#: Bytes a point costs in the heaviest tile pass (its record, its cell, the vegetation
#: test's 14 neighbours with their distances, covariance features), measured with
#: ``scripts/bench_scale.py``.
BYTES_PER_POINT = 400

#: Share of the memory available that the tiles of all workers may take.
TILE_MEMORY_SHARE = 0.5

#: Most points a work tile holds, buffer included, however much memory there is: a
#: tile's work gains nothing from being larger, and smaller tiles keep every worker
#: busy and the memory of a run the same whatever its area. A worker's imports take
#: about 250 MB; a tile of this many points adds about 200 MB to it at its heaviest
#: pass, so the run's peak hardly depends on how full its tiles are. On the Delft
#: strip copied 2 x 2, 4 x 4 and 10 x 10 (``scripts/bench_scale.py``) this budget's
#: 128 m tiles against 1.5 M points' 256 m ones: peak 0.85 -> 0.74, 1.09 -> 0.85 and
#: 1.48 -> 1.39 GB, wall time 2 to 6 % longer (the buffers' share of the points).
TILE_POINTS = 800_000


def plan(r: Run) -> None:
    """The product grid (cell size from the data), its work tiles and their buffers."""
    s, cfg = r.source, r.config
    u = s.units
    spacing = s.summary.spacing
    gsd = r.auto.get("stereo", {}).get("ground_sample_distance")
    if cfg.dsm.resolution:
        res, why = u.length(cfg.dsm.resolution), "config"
    elif gsd and spacing < gsd:  # pairs over the same ground add points, not detail
        res, why = dsm_stage.choose_resolution(gsd, u)
        why = why.replace("mean point spacing", "stereo: ground sample distance (the points are denser)")
    else:
        res, why = dsm_stage.choose_resolution(spacing, u)
    r.auto["dsm.resolution"] = {"value": res, "unit": u.name, "reason": why}
    r.auto["point_spacing"] = {"value": round(spacing, 3), "unit": u.name}
    lo, hi = s.summary.bounds
    if r.stereo == "frame":
        # the grid spans the sparse points too, so a part of the common area the matching
        # lost shows as empty cells rather than as a smaller grid
        world = s.scene.sparse + s.scene.offset
        lo, hi = np.minimum(lo, world.min(axis=0)), np.maximum(hi, world.max(axis=0))
    cells = float(np.ceil((hi[0] - lo[0]) / res + 1) * np.ceil((hi[1] - lo[1]) / res + 1))
    require_memory(cells * GRID_BYTES_PER_CELL, f"a DSM of {cells:.3g} cells of {res:g} {u.name}",
                   "choose coarser cells (--set dsm.resolution=...) or cut the input into tiles",
                   source=r.inputs.input_path)
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], res)
    radius = vegetation.neighbour_radius(spacing, u)
    buffers = {
        "vegetation": int(math.ceil(2 * radius / res)) + 2,
        "reference": int(math.ceil(u.length(passes.REFERENCE_DISTANCE + 0.25) / res)) + 1,
    }
    r.auto["vegetation.radius"] = {"value": round(radius, 3), "unit": u.name,
                                   "reason": "farthest neighbour of the vegetation test: 8 m, or 20 point spacings"}
    density = s.summary.count / max(float(np.prod(hi[:2] - lo[:2])) / res**2, 1.0)
    workers = r.executor.workers if r.executor.client is None else 1
    budget = min(TILE_POINTS, TILE_MEMORY_SHARE * available_memory() / BYTES_PER_POINT / max(workers, 1))
    size = None
    if cfg.tiles.size is not None:
        size = max(1, int(round(u.length(cfg.tiles.size) / res)))
    buffer = max(buffers.values())
    require_memory((BLOCK + 2 * buffer) ** 2 * density * BYTES_PER_POINT * max(workers, 1) / TILE_MEMORY_SHARE,
                   f"the smallest work tile ({BLOCK + 2 * buffer} cells of {res:g} {u.name} a side, buffer included)",
                   "give the run more memory, or fewer workers", source=r.inputs.input_path)
    tile_grid, reason = plan_tiles(shape, buffer, density, budget=budget, size=size)
    per_block = _block_points(r, transform, shape)
    tiles = tile_grid.tiles(per_block > 0)
    r.auto["tiles"] = {"size": {"value": round(tile_grid.size * res, 3), "unit": u.name, "cells": tile_grid.size,
                                "reason": reason},
                       "count": len(tiles),
                       "buffer": {"value": round(tile_grid.buffer * res, 3), "unit": u.name,
                                  "reason": "twice the vegetation test's neighbour radius: the widest look across "
                                            "a tile's edge of any per-point rule"}}
    spec = passes.Spec(s.store, transform, shape, r.cache / f"tiles-{tile_grid.size}", cfg, u, s.summary,
                       r.stereo)
    per = tile_grid.size // BLOCK
    points = [int(per_block[t.key[0] * per:(t.key[0] + 1) * per, t.key[1] * per:(t.key[1] + 1) * per].sum())
              for t in tiles]
    r.grid = Grid(transform, shape, tiles, spec, buffers, points)


def _block_points(r: Run, transform, shape) -> np.ndarray:
    """(rows, cols) int64 points in each block (tiles without any are skipped)."""
    blocks = (-(-shape[0] // BLOCK), -(-shape[1] // BLOCK))
    out = np.zeros(blocks[0] * blocks[1], np.int64)
    for cloud in r.source.store.chunks():
        row, col = cell_rowcol(cloud.xyz, transform)
        out += np.bincount((row // BLOCK) * blocks[1] + col // BLOCK, minlength=out.size)
    return out.reshape(blocks)


def make_dsm(r: Run) -> None:
    """The DSM: the tiles' highest points, holes filled; for stereo, the area both images see."""
    g, s, cfg, u = r.grid, r.source, r.config.dsm, r.units
    stereo = r.stereo
    res = g.transform.a
    defaults = HOLE_AREA["lidar" if stereo is None else stereo]
    hole_area = cfg.max_hole_area if cfg.max_hole_area is not None else defaults[0]
    r.auto["dsm.max_hole_area"] = {"value": hole_area, "reason": "config" if cfg.max_hole_area is not None else defaults[1]}
    gtransform, gshape = ground_stage.surface_grid(s.summary.bounds, ground_stage.surface_cell(r.config.ground, u, res)[0])
    paths = r.passes["surface"] = r.tiles("surface", passes.surface, [(gtransform, gshape)] * len(g.tiles))
    raw = g.place(paths, "dsm")
    count = g.place(paths, "count", fill=0.0)
    zmin = np.full(gshape, np.nan)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    first = 0
    for path in paths:
        with np.load(path) as data:
            (r0, c0), (n, m) = data["zmin_origin"], data["zmin"].shape
            zmin[r0:r0 + n, c0:c0 + m] = np.fmin(zmin[r0:r0 + n, c0:c0 + m], data["zmin"])
            lo, hi = np.minimum(lo, data["surface_lo"]), np.maximum(hi, data["surface_hi"])
            first += int(data["first_returns"])
    crs = s.crs
    method = "highest point per cell"
    observed = consistent = foreground = None
    if stereo is not None and "observed" in s.summary.dtypes:
        observed = g.place(paths, "observed", fill=0.0)
        if "consistent" in s.summary.dtypes:
            consistent = g.place(paths, "consistent", fill=0.0)
            foreground = g.place(paths, "foreground", fill=0.0)
        method = (f"{'median' if stereo == 'satellite' else 'highest'} observed point per cell and pair, "
                  "median over the pairs")
    raw_dsm = g.raster(raw, crs)
    area = None
    common = None
    if stereo == "frame":
        pairs = s.stereo["pairs"]
        matched = (observed if observed is not None else count) > 0
        from recon3d.stereo import coverage

        common = coverage.common_area(s.scene, pairs, raw_dsm, matched, u)
        area = common & ~coverage.holes_both_saw(s.scene, pairs, raw_dsm, common, int(u.area(SEEN_HOLE_AREA) / res**2))
    data = dsm_stage.fill_small_holes(raw, int(u.area(hole_area) / res**2), rim="low" if stereo else "mean", area=area)
    dsm = g.raster(data, crs, product="DSM", method=method)
    filled = (count == 0) & np.isfinite(dsm.data)
    unobserved = consistent_cells = foreground_cells = None
    if observed is not None and not s.summary.all_observed:
        unobserved = (observed == 0) & np.isfinite(dsm.data)
        if consistent is not None:
            consistent_cells, foreground_cells = consistent > 0, foreground > 0
    if stereo == "satellite":  # products only where both images see the ground
        from recon3d.stereo import coverage

        common = coverage.rpc_common_area(s.scene, s.stereo.get("relative_bias_px", (0.0, 0.0)), dsm)
        dsm.data[~common] = np.nan
        filled &= common
        if unobserved is not None:
            unobserved &= common
    upper_median = g.place(paths, "dsm_upper_median") if stereo == "frame" and observed is not None else None
    r.surface = Surface(dsm, filled, unobserved, consistent_cells, common, first,
                        (lo, hi), (zmin, gtransform), upper_median, foreground_cells)
    if stereo == "frame":
        _check_common_area(r)


#: Largest hole (m2) of a frame-stereo DSM filled although tie points seen by both
#: images of a pair lie in it (see :func:`recon3d.stereo.coverage.holes_both_saw`).
SEEN_HOLE_AREA = 200.0


def _check_common_area(r: Run) -> None:
    """Frame stereo: how much of the common area the DSM fills; a warning below
    :data:`~recon3d.stereo.coverage.MIN_COMMON_FILLED` percent, naming where the empty cells are."""
    from recon3d.stereo import coverage

    sf = r.surface
    area = coverage.common_area_fill(sf.common_area, sf.dsm, sf.filled, sf.unobserved, r.units)
    empty = area.pop("empty_cells", None)
    r.auto["stereo"]["common_area"] = area
    if empty is not None:
        x0, y0, x1, y1 = area["empty_extent"]
        r.warn(
            f"the DSM fills {area['filled_percent']:.0f} % of the {area['area_m2']:.0f} m2 that the matched "
            f"image pairs both see (expected >= {coverage.MIN_COMMON_FILLED:.0f} %); {empty} cells are empty, "
            f"within x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f}"
        )


def classify_ground(r: Run) -> None:
    """Ground points: the filter's terrain on the minimum surface, then each tile's points against it."""
    cfg, u, s = r.config.ground, r.units, r.source.summary
    params: dict = {}
    if cfg.method == "provider":
        if "classification" not in s.dtypes or not s.ground_points:
            raise InputError("ground.method='provider' but the input has no ground points (class 2)")
        method, noise, terrain = "provider", 0.0, None
        params["method"] = "provider"
    else:
        if s.count < 3:
            raise InputError(f"the point cloud has {s.count} point(s); ground filtering needs at least 3")
        params["method"] = None  # chosen once the surface's noise is measured
        cell, why = ground_stage.surface_cell(cfg, u, r.grid.transform.a)
        params["cell"] = {"value": cell, "reason": why}
        if s.quality_cut is not None:
            params["quality_cut"] = {"value": s.quality_cut, "reason": ground_stage.QUALITY_CUT_REASON}
        surface = ground_stage.minimum_surface(*r.surface.ground_surface, cfg, u, params)
        r.surface.ground_surface = None  # the filter's alone
        method, why = ground_stage.pick_method(cfg, "number_of_returns" in s.dtypes, surface.noise * u.vertical)
        params["method"] = {"value": method, "reason": why}
        terrain = ground_stage.terrain(surface, method, u)
        if r.stereo == "frame":
            terrain, raised = ground_stage.fill_pits(terrain, u.length(ground_stage.PIT_WIDTH),
                                                     u.height(ground_stage.PIT_DEPTH), surface.measured)
            params["pits_filled"] = {"value": raised, "reason": ground_stage.PIT_REASON}
        noise = surface.noise
        params.update(ground_stage.ground_tolerances(cfg, u, noise)[2])
    g = r.grid
    args = []
    for tile in g.tiles:
        window = None
        if terrain is not None:  # two cells around the core: the bilinear sample and the gradient
            window = terrain.window(*passes.cover(g.spec.grid(tile).bounds, terrain.transform, terrain.shape, margin=2))
        args.append((window, noise, method))
    paths = r.passes["ground"] = r.tiles("ground", passes.ground, args)
    r.auto["ground"] = params
    # the stages after the filter take the noise as run.json records it (to the mm)
    r.terrain = Terrain(None, None, params.get("noise", {}).get("value", 0.0) / u.vertical)
    counts = np.zeros(5, np.int64)
    ground_points = 0
    for path in paths:
        with np.load(path) as data:
            ground_points += int(data["is_ground"].sum())
            if "filter_counts" in data:
                counts += data["filter_counts"]
    log.info("%s: %d of %d points ground (%.1f %%)", method, ground_points, s.count, 100 * ground_points / s.count)
    if s.provider_classes:
        from recon3d.quality import evaluate

        r.report["ground_filter"] = evaluate.filter_scores(counts)


def make_dtm(r: Run) -> None:
    """The DTM from the ground points' cells (breaklines and spot heights honoured), and the nDSM."""
    g, s = r.grid, r.source
    paths = r.passes["ground"]
    mean = g.place(paths, "mean")
    count = g.place(paths, "count", fill=0.0)
    noise = r.terrain.noise
    constraints = None
    if s.constraints is not None:
        lines, points = s.constraints
        constraints = np.concatenate([dtm_stage.densify_lines(lines, g.transform.a / 2), points])
    sf = r.surface
    dtm = dtm_stage.dtm_from_cells(mean, count, sf.dsm, noise=noise, constraints=constraints)
    if r.stereo == "frame":
        dtm = _refill_under_ground_ties(r, dtm, mean, count, noise, constraints)
    if r.stereo == "satellite":  # no extrapolation beyond what both images see
        dtm.data[~np.isfinite(sf.dsm.data)] = np.nan
    elif sf.unobserved is not None:
        _lower_unseen_guesses(r, dtm, noise)
        lift = dtm_stage.raise_to_terrain(sf.dsm, dtm)
        r.auto["dsm.raised_to_dtm"] = {
            "value": int(np.count_nonzero(lift)),
            "over_noise": int(np.count_nonzero(lift > 3.0 * noise)),
            "max": round(float(lift.max(initial=0.0)), 2),
            "reason": "cells below the DTM (holes filled from the low side of their rim on sloping ground, "
                      "mismatches below the ground): set to the DTM; over_noise: raised by more than 3 times "
                      "the ground points' noise",
        }
        _check_matched_in_view(r, noise)
    r.terrain.dtm = dtm
    r.terrain.ndsm = dtm_stage.make_ndsm(sf.dsm, dtm)


def _refill_under_ground_ties(r: Run, dtm: Raster, mean: np.ndarray, count: np.ndarray, noise: float,
                              constraints: np.ndarray | None) -> Raster:
    """Frame stereo: the DTM again, with its regions sunk under the ground tie points
    inside them (:func:`recon3d.stereo.check.sunk_under_ground_ties`) interpolated from
    their rim and those tie points instead of from the ground cells in them."""
    from recon3d.stereo.check import GROUND_TIE_BAND, GROUND_TIE_MAX_SPREAD, SUNK_MARGIN, sunk_under_ground_ties

    scene, u = r.source.scene, r.units
    if scene is None or not len(scene.sparse):
        return dtm
    sunk, ties = sunk_under_ground_ties(dtm, scene.sparse + scene.offset, margin=u.height(SUNK_MARGIN),
                                        band=u.height(GROUND_TIE_BAND), max_spread=u.height(GROUND_TIE_MAX_SPREAD))
    r.auto["dtm.sunk_under_ground_ties"] = {
        "value": int(sunk.sum()), "tie_points": len(ties),
        "reason": f"cells of regions where the DTM lay more than {SUNK_MARGIN:g} m under the plane of the ground tie "
                  f"points and a ground tie point inside stood more than {SUNK_MARGIN:g} m above it (a patch of "
                  "mismatches taken for the ground): interpolated from their rim and the ground tie points in them",
    }
    if not sunk.any():
        return dtm
    r.terrain.sunk = sunk
    depth = float(np.nanmax(ties[:, 2] - dtm.sample(ties[:, 0], ties[:, 1], bilinear=False)))
    area = np.count_nonzero(sunk & np.isfinite(r.surface.dsm.data)) * (dtm.resolution * u.horizontal) ** 2
    r.warn(f"the DTM lay up to {depth * u.vertical:.1f} m under {len(ties)} ground tie point(s) over "
           f"{area:.0f} m2 of the data (mismatches taken "
           "for the ground): interpolated again from those tie points and the region's rim; the matching there is "
           "doubtful (run.json dtm.sunk_under_ground_ties)")
    fixed = ties if constraints is None else np.concatenate([constraints, ties])
    return dtm_stage.dtm_from_cells(np.where(sunk, np.nan, mean), np.where(sunk, 0.0, count), r.surface.dsm,
                                    noise=noise, constraints=fixed)


def _lower_unseen_guesses(r: Run, dtm: Raster, noise: float) -> None:
    """Stereo DSM cells filled in at a height where both images of a matched pair would
    have seen them are hidden ground: they take the DTM (see
    :func:`recon3d.stereo.coverage.unseen_guesses`); so do guesses the images agree
    with behind a building (:func:`_lower_agreed_guesses`)."""
    from recon3d.stereo import coverage

    sf, u = r.surface, r.units
    unjudged = sf.unobserved if sf.consistent is None else sf.unobserved & ~sf.consistent
    tolerance = max(u.height(0.5), 3.0 * noise)
    lower = coverage.unseen_guesses(r.source.scene, r.source.stereo["pairs"], sf.dsm, dtm, unjudged, sf.matched, u,
                                    tolerance=tolerance, min_area=u.area(4.0))
    sf.dsm.data[lower] = dtm.data[lower]
    agreed = _lower_agreed_guesses(r, dtm, lower, tolerance) if sf.consistent is not None else np.zeros_like(lower)
    r.auto["dsm.hidden_ground"] = {
        "value": int((lower | agreed).sum()),
        "agreed": int(agreed.sum()),
        "reason": "cells no pixel matched, filled in above the DTM at a height both images of a pair would have "
                  "seen, or where at the DTM's height one image of a pair sees them over the matched surface and "
                  "the other does not, or neither does although both frame them and no matched building encloses "
                  "them (a narrow street), and not inside a hole of a matched roof: set to the DTM; agreed: of "
                  "these, guesses the images agree with, lowered only by the second test and only in regions "
                  "whose rim is at least half ground",
    }


def _lower_agreed_guesses(r: Run, dtm: Raster, lowered: np.ndarray, tolerance: float) -> np.ndarray:
    """Frame stereo: the guesses the images agree with (photo-consistent, not filled
    beyond an occlusion's width) that are hidden ground all the same, set to the DTM.

    At a wide angle the street a building hides from one image is often filled in at
    the roof's height, and the images agree with that guess by chance (on the rendered
    family such cells held 42 % of a wide-angle survey's squared DSM error). A region
    of them is judged only where it opens onto the ground
    (:func:`~recon3d.stereo.coverage.open_to_ground`: half its rim matched ground or
    hidden ground just lowered), and only by the occlusion test: at the DTM's height
    one image of a pair sees it over the matched surface and the other does not. A roof
    face the matcher missed opens onto its roof; a crown or a small roof it missed whole
    hides no ground from one image only, as hidden street does behind a matched building.

    Returns
    -------
    (rows, cols) bool
        The cells lowered.
    """
    from recon3d.stereo import coverage

    sf, u = r.surface, r.units
    dsm = sf.dsm.data
    agreed = sf.unobserved & sf.consistent & ~sf.foreground & ~lowered & (dsm > dtm.data + tolerance)
    ground = (sf.matched & (np.abs(dsm - dtm.data) <= tolerance)) | lowered
    candidates = coverage.open_to_ground(agreed, ground, sf.matched | lowered)
    # judged with the guesses around them, so that a region's area counts them all
    judged = sf.unobserved & (~sf.consistent | candidates)
    lower = candidates & coverage.unseen_guesses(r.source.scene, r.source.stereo["pairs"], sf.dsm, dtm, judged,
                                                 sf.matched, u, tolerance=tolerance, min_area=u.area(4.0),
                                                 behind_only=True)
    dsm[lower] = dtm.data[lower]
    return lower


def _check_matched_in_view(r: Run, noise: float) -> None:
    """Frame stereo: the common area split into matched, hidden from one image and
    missed by the matcher (on the final DSM); a warning when the matcher matched less
    than :data:`~recon3d.stereo.coverage.MIN_MATCHED_OF_VISIBLE` percent of what both
    images see."""
    from recon3d.stereo import coverage

    sf, u = r.surface, r.units
    if r.stereo != "frame" or sf.common_area is None:
        return
    split = coverage.unmatched_in_view(r.source.scene, r.source.stereo["pairs"], sf.dsm, sf.common_area, sf.matched,
                                       tolerance=max(u.height(0.5), 3.0 * noise))
    r.auto["stereo"]["common_area"].update(split)
    if split["matched_of_visible_percent"] < coverage.MIN_MATCHED_OF_VISIBLE:
        r.warn(
            f"the matcher matched {split['matched_of_visible_percent']:.0f} % of the area both images of a pair see "
            f"unhidden (expected >= {coverage.MIN_MATCHED_OF_VISIBLE:.0f} %): {split['missed_percent']:.0f} % of the "
            "common area is filled in although both images show it (texture-poor or repetitive surfaces, "
            "a wrong disparity range or orientation)"
        )


def classify_vegetation(r: Run) -> None:
    """Vegetation points (neighbourhoods read across the tiles' edges) and the cells' evidence."""
    g, u, s = r.grid, r.units, r.source.summary
    cfg = r.config.buildings
    noise = r.terrain.noise
    radius = r.auto["vegetation.radius"]["value"]
    buffer = g.buffers["vegetation"]
    survey = vegetation.Survey(s.returns, s.colour)
    dtm = r.terrain.dtm
    windows = [dtm.window(*(slice(max(w.start - 1, 0), w.stop + 1) for w in t.window(buffer, g.shape)))
               for t in g.tiles]
    paths = r.tiles("vegetation_features", passes.vegetation_features,
                    [(w, survey, noise, radius, buffer) for w in windows])
    counts = np.zeros(4, np.int64)
    for path in paths:
        with np.load(path) as data:
            counts += data["counts"]
    survey = passes.with_counts(survey, counts)
    tolerance = vegetation.plane_tolerance(cfg, u, noise)
    paths = r.tiles("vegetation_decide", passes.vegetation_decide, [(survey, noise, buffer, tolerance)] * len(g.tiles))
    share = g.place(paths, "share", np.float32, fill=0.0)
    planar = g.place(paths, "planar", np.float32, fill=1.0)
    # read by the detection a strip at a time: four times the DSM's cells never held whole
    fine = detect.FineSurface(g.mosaic(paths, "fine_z", factor=detect.FINE),
                              g.mosaic(paths, "fine_vegetation", bool, False, factor=detect.FINE))
    finite = np.count_nonzero(np.isfinite(r.surface.dsm.data))
    area = finite * u.area(1.0) ** -1 * g.transform.a**2
    density = float(r.surface.first_returns / area) if area > 0 else 0.0
    r.evidence = Evidence(share, planar, fine, tolerance, density)


#: Cells of the grid from which the idle workers stop before the building detection:
#: it holds this process's largest grids (the nDSM, the evidence, the blobs and their
#: labels: about 80 bytes a cell with the block split cut a window at a time, 120
#: before), which beyond 2 M cells (0.5 km2 at 0.5 m) outweigh two idle workers'
#: memory, so the run's peak is lower without them; below, starting them again (about
#: a second) costs more. The 64 x Delft survey (4.2 M cells, 2 workers): peak 0.97 ->
#: 0.89 GB; at 100 x (6.6 M cells) the workers hold 0.58 GB after the vegetation pass.
STOP_WORKERS_CELLS = 2_000_000


def find_buildings(r: Run) -> None:
    """Buildings: the given footprints aligned with the data, or blobs of the nDSM; their heights."""
    cfg, u, s = r.config.buildings, r.units, r.source
    sf, t, ev = r.surface, r.terrain, r.evidence
    if sf.dsm.data.size > STOP_WORKERS_CELLS:
        r.executor.close()  # they start again for the outlines
    if s.footprints is not None:
        evidence = detect.building_evidence(t.ndsm, ev.share, cfg, u)
        polygons, shifts, support = align.align_footprints(
            [f.polygon for f in s.footprints], evidence, u.length(cfg.footprint_shift)
        )
        ids = [f.id for f in s.footprints]
        attrs = [
            dict(f.attributes, source="footprints", shift_x=round(float(d[0]), 3), shift_y=round(float(d[1]), 3),
                 building_support=None if not np.isfinite(v) else round(float(v), 3))
            for f, d, v in zip(s.footprints, shifts, support, strict=True)
        ]
        no_building = [i for i, v in zip(ids, support, strict=True) if np.isfinite(v) and v < 0.5]
        if no_building:
            r.notes.append(f"{len(no_building)} footprints have no building under them: " + ", ".join(no_building[:20]))
        if len(shifts):
            r.auto["footprint_shift"] = {"value": np.round(np.median(shifts, axis=0), 3).tolist(),
                                         "reason": "median map-to-data shift found by aligning footprints with the nDSM"}
    else:
        ndsm = t.ndsm
        if r.stereo == "satellite" and sf.unobserved is not None:  # only where matched
            ndsm = ndsm.like(np.where(sf.unobserved, np.nan, ndsm.data), **ndsm.tags)
        blobs = detect.find_blobs(ndsm, ev.share, cfg, u, planar=ev.planar, point_density=ev.density,
                                  colour=s.summary.colour is not None)
        polygons = detect.detect_buildings(ndsm, ev.share, cfg, u, dtm=t.dtm, fine=ev.fine, mapper=_mapper(r),
                                           blobs=blobs)
        if r.stereo == "satellite" and sf.unobserved is not None:
            polygons = _on_observed_ground(r, polygons)
        if r.stereo == "frame":
            polygons = _on_measured_cells(r, polygons)
        ids = [f"b{i + 1:04d}" for i in range(len(polygons))]
        attrs = [{"source": "detected", **_rounded(detect.blob_descriptors(p))} for p in polygons]
        if r.stereo == "frame" and cfg.image_outlines and polygons:
            polygons = _outlines_from_images(r, polygons, attrs)
    labels = detect.label_footprints(polygons, sf.dsm)
    if sf.upper_median is not None:
        _median_outside_buildings(r, labels)
        _lower_unsupported_guesses(r)
        t.ndsm = dtm_stage.make_ndsm(sf.dsm, t.dtm)
    heights = measure_heights(
        polygons, labels, sf.dsm, t.dtm, percentile=cfg.roof_percentile, min_height=u.height(cfg.min_height)
    )
    buildings = []
    for i, poly in enumerate(polygons):
        attrs[i].update(cells=int(heights.cells[i]), raised_share=round(float(heights.raised_share[i]), 3))
        buildings.append(Building(ids[i], poly, heights.ground_z[i], heights.roof_z[i], attributes=attrs[i]))
    if s.footprints is None:  # parts of a block split at height jumps: Building + BuildingParts
        # the blobs' own mask, unless it was cut to the matched cells (satellite)
        raised = blobs.mask if ndsm is t.ndsm else detect.building_mask(t.ndsm, ev.share, cfg, u)
        blocks.assign_blocks(buildings, labels, raised, min_shared=u.length(cfg.min_edge))
    # the date of the data, not of the run: the same input gives the same bytes
    meta = {"referenceDate": s.reference_date or r.date}
    if not s.reference_date:
        r.auto["reference_date"] = {"value": r.date, "reason": "the input holds no date: the day the run started "
                                    "(SOURCE_DATE_EPOCH sets another)"}
    r.labels = labels
    ev.planar = None  # the detection's alone
    r.city = CityModel(buildings, s.crs, LocalFrame.around(s.summary.bounds[0], step=u.length(100.0)), meta)
    _spill_grids(r)


def _spill_grids(r: Run) -> None:
    """The whole-area grids mapped from files while the workers build and scan the
    solids: this process's memory no longer grows with the area (see :mod:`spill`)."""
    sf, t = r.surface, r.terrain
    for raster in (sf.dsm, t.dtm, t.ndsm):
        raster.data = r.grids(raster.data)
    for name in ("filled", "unobserved", "consistent", "common_area", "foreground"):
        if getattr(sf, name) is not None:
            setattr(sf, name, r.grids(getattr(sf, name)))
    r.evidence.share = r.grids(r.evidence.share)
    r.labels = r.grids(r.labels)


def _median_outside_buildings(r: Run, labels: np.ndarray) -> None:
    """Frame stereo, once the footprints are known: matched DSM cells outside them and
    outside the crowns take the median of each pair's points (of an even count the
    higher middle point, a height the pair saw) instead of its highest (see
    :func:`recon3d.terrain.dsm.grid_stereo`, ``"upper_median"``).

    A census window straddling a wall carries a point or two of a roof onto the street,
    and a pair's highest point keeps them; so does, along a wall, a pixel at the roof's
    edge, triangulated at its centre up to half a pixel beyond the wall. On open ground
    the median also drops the upward bias of the highest of a pair's noisy points.
    Inside the footprints the highest stays: there it keeps the roof's edge on the
    roof. In the crowns (cells whose upper points are mostly vegetation) it stays too:
    a crown's few matched points are its top, and the matcher already misses much of
    it. A cell the wall crosses may take any height between the street and the roof
    (the truth holds both), so the median costs nothing there. The plain median (not
    the upper) put a roof cell the detected footprint had missed, with as many street
    points as roof points, halfway down (a roof check point of portrait_wide 8 m low).
    The README gives the figures on the rendered surveys."""
    sf = r.surface
    median = sf.upper_median
    lower = (labels == 0) & ~r.evidence.vegetated & sf.matched & (median < sf.dsm.data)  # NaN compares False
    sf.upper_median = None
    _lower_dsm(r, "dsm.median_outside_buildings", lower, median,
               "matched cells outside the building footprints and the crowns: the median of each pair's points per "
               "cell, not its highest, so that the points of a roof carried onto the street by the matcher or "
               "triangulated beyond its wall do not set the cell, nor the highest of a pair's noisy points on open "
               "ground (inside the footprints the highest keeps the roof's edge, in the crowns their top)")


def _lower_dsm(r: Run, key: str, cells: np.ndarray, heights: np.ndarray, reason: str) -> None:
    """Set the DSM's ``cells`` to ``heights``, never below the DTM, and record how many in
    run.json under ``key`` with ``reason``."""
    dsm, dtm = r.surface.dsm.data, r.terrain.dtm.data
    dsm[cells] = np.fmax(heights[cells], dtm[cells])
    r.auto[key] = {"value": int(cells.sum()), "reason": reason}


#: Metres around a guessed DSM cell searched for matched cells, and metres above the
#: highest of them at which the guess is lowered to it (:func:`_lower_unsupported_guesses`).
SUPPORT_REACH = 1.0
SUPPORT_HEIGHT = 1.0


def _lower_unsupported_guesses(r: Run) -> None:
    """Frame stereo: a cell no pixel matched that stands more than :data:`SUPPORT_HEIGHT`
    above every matched cell within :data:`SUPPORT_REACH` takes the highest of them (see
    :func:`recon3d.stereo.coverage.unsupported_guesses`)."""
    from recon3d.stereo import coverage

    sf, u = r.surface, r.units
    guessed = sf.filled if sf.unobserved is None else sf.unobserved
    lower, highest = coverage.unsupported_guesses(sf.dsm, sf.matched, guessed, reach=u.length(SUPPORT_REACH),
                                                  height=u.height(SUPPORT_HEIGHT))
    _lower_dsm(r, "dsm.unsupported_guesses", lower, highest,
               f"cells no pixel matched standing more than {SUPPORT_HEIGHT:g} m above every matched cell within "
               f"{SUPPORT_REACH:g} m: lowered to the highest of them (a guess the images give nothing to hold up)")


def _mapper(r: Run):
    """``mapper(func, jobs)`` of per-building work: on the run's workers from
    :data:`_PARALLEL_FROM` jobs on, in this process below (starting workers costs more)."""
    def mapper(func, jobs):
        return r.executor.map(func, jobs, workers=1 if len(jobs) < _PARALLEL_FROM else None)

    return mapper


#: Least share of the ring of cells around a detected satellite building (2 to 6 m out)
#: that must hold matched observations: a "building" amid filled-in cells stands on
#: terrain nobody saw.
MIN_OBSERVED_RING = 0.5


def _on_observed_ground(r: Run, polygons: list) -> list:
    """The detected outlines whose surrounding terrain was observed (see :data:`MIN_OBSERVED_RING`)."""
    from scipy import ndimage

    if not polygons:
        return polygons
    dsm = r.surface.dsm
    labels = detect.label_footprints(polygons, dsm)
    near = int(np.ceil(r.units.length(2.0) / dsm.resolution))
    far = int(np.ceil(r.units.length(6.0) / dsm.resolution))
    reach = ndimage.grey_dilation(labels, size=2 * far + 1)  # the label of a building within 6 m
    close = ndimage.grey_dilation(labels, size=2 * near + 1) > 0
    ring = (reach > 0) & ~close
    seen = ring & np.isfinite(dsm.data) & ~r.surface.unobserved
    n = len(polygons) + 1
    share = np.bincount(reach[seen], minlength=n) / np.maximum(np.bincount(reach[ring], minlength=n), 1)
    keep = share[1:] >= MIN_OBSERVED_RING
    if not keep.all():
        r.notes.append(f"{int((~keep).sum())} detected buildings dropped: the terrain around them was not matched")
    return [p for p, k in zip(polygons, keep, strict=True) if k]


#: Largest share of a detected frame-stereo building's cells that may be holes of the
#: DSM filled in from their rim (no point at all): a blob of filled cells is the rim of
#: a hole the matcher left (on 18 surveys of the frame family at 1000 px: 32 of 75 false
#: detections, 4 of 748 true ones, all mostly holes themselves).
MAX_FILLED_SHARE = 0.5


def _on_measured_cells(r: Run, polygons: list) -> list:
    """The detected outlines at most :data:`MAX_FILLED_SHARE` of whose cells are filled-in holes."""
    labels = detect.label_footprints(polygons, r.surface.dsm)
    n = len(polygons) + 1
    filled = np.bincount(labels[r.surface.filled], minlength=n) / np.maximum(np.bincount(labels.ravel(), minlength=n), 1)
    keep = filled[1:] <= MAX_FILLED_SHARE
    if not keep.all():
        r.notes.append(f"{int((~keep).sum())} detected buildings dropped: more than {MAX_FILLED_SHARE:.0%} of their "
                       "cells are holes of the DSM filled in, no match stands there")
    return [p for p, k in zip(polygons, keep, strict=True) if k]


def _outlines_from_images(r: Run, polygons: list, attrs: list[dict]) -> list:
    """Frame stereo: the detected outlines moved edge by edge to the eaves two images
    agree on (:mod:`recon3d.buildings.image_outline`); ``outline_source`` says which
    outline each building kept."""
    from recon3d.buildings import image_outline
    from recon3d.stereo import ortho

    if r.source.views is None:
        r.source.views = ortho.frame_views(r.source.scene)
    found = image_outline.refine_outlines(polygons, r.source.views, r.surface.dsm, metre=r.units.length(1.0))
    for a, f in zip(attrs, found, strict=True):
        a.update(outline_source=f.source, outline_moved_share=round(f.moved_share, 3),
                 outline_shift=round(f.mean_shift, 3))
    moved = sum(f.source == "images" for f in found)
    r.auto["image_outlines"] = {
        "value": moved, "of": len(found),
        "reason": "outlines moved to the eaves where the two most nadir images agree within "
                  f"{image_outline.AGREEMENT} m (set buildings.image_outlines=false to keep the nDSM outlines)",
    }
    return [f.polygon for f in found]


def _rounded(values: dict) -> dict:
    return {k: round(float(v), 3) for k, v in values.items()}


#: Buildings from which ``build_solids`` uses every CPU by default (a building takes
#: 30 ms at the median, a worker process about 1 s to start and import Open3D).
_PARALLEL_FROM = 32


def build_solids(r: Run) -> None:
    """Every building's solids (LoD1, LoD2.2, LoD1.3 fallbacks) from the points on its roof."""
    import shapely

    u, city = r.units, r.city
    lo, hi = r.source.summary.bounds
    extent = shapely.box(lo[0], lo[1], hi[0], hi[1])
    built, boxes = [], []
    for b in city:
        reason = None
        poly = lod.clean_footprint(b.footprint, u.length(0.01))
        if poly is None:
            reason = "degenerate_footprint"
        elif not poly.intersects(extent):
            reason = "outside_data"
        elif b.attributes["cells"] == 0 or not np.isfinite(b.roof_z):
            reason = "no_points"
        elif not np.isfinite(b.ground_z):
            reason = "no_terrain"
        elif b.height < u.height(0.5):
            reason = "too_low"
        if reason:
            b.status, b.reason = "failed", reason
            continue
        b.footprint = poly
        built.append(b)
        boxes.append(poly.bounds)
    sources, counts = _building_points(r, np.array(boxes, np.float64).reshape(-1, 4))
    jobs = [(b.footprint, (paths, k), b.ground_z, b.roof_z, city.frame, r.config.lod, u)
            for k, (b, paths) in enumerate(zip(built, sources, strict=True))]
    if r.workers:
        workers, why = r.workers, "given (--workers, or run(workers=))"
    elif len(jobs) < _PARALLEL_FROM:
        workers, why = 1, f"fewer than {_PARALLEL_FROM} buildings: starting processes (about 1 s) costs more than it saves"
    else:
        workers, why = default_workers(), "the CPUs this process may use (affinity, container quota)"
    if r.executor.client is not None:
        why = "the Dask cluster's workers"
    r.auto["workers"] = {"value": min(workers, max(len(jobs), 1)), "reason": why}
    done = None if r.progress is None else lambda k: r.progress(f"{k}/{len(jobs)} buildings")
    from recon3d.quality.roofs import validity_attributes

    # the largest first, so that no worker is left with a big building at the end
    # (longest processing time first); each result goes back to its building
    order = sorted(range(len(jobs)), key=lambda k: -counts[k])
    results = [None] * len(jobs)
    for k, res in zip(order, r.executor.map(_build_lods, [jobs[k] for k in order], done=done, workers=workers),
                      strict=True):
        results[k] = res
    empty = dict(zip((b.id for b in city), _empty_share(r)[1:], strict=False))
    for b, (res, fit) in zip(built, results, strict=True):
        b.solids.update(res.solids)
        b.status, b.reason = res.status, res.reason
        b.attributes.update(roof_type=res.roof_type, roof_planes=len(res.planes))
        if np.isfinite(res.roof_rms):
            b.attributes["roof_point_rms_m"] = round(float(res.roof_rms) * u.vertical, 3)
        # the share of the footprint's cells without a point, as roofer reports it
        b.attributes.update({"footprint_empty_share": round(float(empty.get(b.id, 0.0)), 3), **fit})
        b.attributes.update(validity_attributes(res.validity))
    if r.stereo is None and r.source.footprints is None:
        _drop_crowns(r)
    failed = [b.id for b in city if not b.solids]
    if failed:
        r.notes.append(f"{len(failed)} footprints got no solid: " + ", ".join(failed[:20]))
    broken = [b.id for b in city if b.reason == "internal_error"]
    if broken:  # a bug in recon3d, not in the data: the traceback went to the log (of a worker)
        r.warn(f"{len(broken)} building(s) kept a lower LoD after an unexpected error in roof modelling "
               f"(reason internal_error; please report it with the log): {', '.join(broken[:20])}")
    missed = sorted(
        ((b.attributes["roof_unmodelled_area_m2"], b.id) for b in city if b.attributes.get("roof_unmodelled_parts")),
        reverse=True,
    )
    if missed:
        r.notes.append(
            f"{len(missed)} buildings have roof parts their model misses ({sum(a for a, _ in missed):.1f} m2 in all; "
            "groups of roof points more than 1 m off, 2 m2 and more: roof_unmodelled_area_m2): "
            + ", ".join(f"{i} {a:.1f} m2" for a, i in missed[:10])
        )


def _drop_crowns(r: Run) -> None:
    """LiDAR without footprints: detected buildings whose roof points fit no plane
    (reason ``no_roof_planes``) and whose nDSM is smooth on less than ``min_smooth_share``
    of their cells are tree crowns, not buildings. A sparse survey of a dense canopy
    (1 point per m2, few multiple returns) gives crowns whose few points look planar to
    the detection; roof modelling then finds no plane in them. They leave the model and
    the footprint labels; their cells go to ``r.evidence.crowns``, whose points above
    the terrain are vegetation in cloud.laz. On the random LiDAR family (180 surveys) no
    building of the truth ever had ``no_roof_planes``; frame stereo, whose real roofs
    do, keeps them (its trees are told by colour)."""
    city, cfg = r.city, r.config.buildings
    picked = [i for i, b in enumerate(city.buildings)
              if b.reason == "no_roof_planes" and b.parent is None and b.attributes.get("source") == "detected"]
    if not picked:
        return
    n = len(city.buildings) + 1
    smooth = detect.smooth_cells(r.terrain.ndsm, cfg, r.units)
    share = np.bincount(r.labels[smooth], minlength=n) / np.maximum(np.bincount(r.labels.ravel(), minlength=n), 1)
    drop = np.zeros(n, bool)
    drop[[i + 1 for i in picked if share[i + 1] < cfg.min_smooth_share]] = True
    if not drop.any():
        return
    r.evidence.crowns = drop[r.labels]
    ids = [b.id for b, d in zip(city.buildings, drop[1:], strict=True) if d]
    city.buildings = [b for b, d in zip(city.buildings, drop[1:], strict=True) if not d]
    r.labels = np.where(drop, 0, np.cumsum(~drop) - 1).astype(r.labels.dtype)[r.labels]
    r.notes.append(f"{len(ids)} detected blobs are tree crowns, not buildings: no roof plane fits their points and "
                   f"their surface is rough (their points are vegetation): {', '.join(ids[:20])}")


def _building_points(r: Run, boxes: np.ndarray) -> tuple[list[list[Path]], np.ndarray]:
    """Where the points that may lie on each building's roof (neither ground nor
    vegetation, inside its bounding box) are kept: the results of the tiles holding some,
    and how many there are. Each building's job reads its own
    (:func:`passes.gather_building_points`), so this process never holds them all."""
    g = r.grid
    args = []
    for tile in g.tiles:
        x0, y0, x1, y1 = g.spec.bounds(tile.rows, tile.cols)
        touch = np.flatnonzero((boxes[:, 0] <= x1) & (boxes[:, 2] >= x0) & (boxes[:, 1] <= y1) & (boxes[:, 3] >= y0))
        args.append((boxes[touch], touch))
    paths = r.tiles("building_points", passes.building_points, args)
    sources: list[list[Path]] = [[] for _ in range(len(boxes))]
    counts = np.zeros(len(boxes), np.int64)
    for path, (_, touch) in zip(paths, args, strict=True):
        with np.load(path) as data:
            here = data["counts"]
        for i in touch[here > 0]:
            sources[i].append(path)
        counts[touch] += here
    return sources, counts


def _empty_share(r: Run) -> np.ndarray:
    """(buildings + 1,) share of each footprint's DSM cells that hold no point (filled from their rim)."""
    labels = r.labels.ravel()
    n = int(labels.max()) + 1 if labels.size else 1
    cells = np.bincount(labels, minlength=n)
    empty = np.bincount(labels[r.surface.filled.ravel()], minlength=n)
    return empty / np.maximum(cells, 1)


def _build_lods(job: tuple) -> tuple[lod.LodResult, dict]:
    """One building's solids, and how well they explain its points (:func:`~recon3d.quality.roofs.fit_quality`):
    a worker process runs this for :func:`build_solids`."""
    from recon3d.quality.roofs import fit_quality

    poly, (paths, index), ground_z, roof_z, frame, config, units = job
    pts = passes.gather_building_points(paths, index)
    res = lod.build_lods(poly, pts, ground_z, roof_z, frame, config, units=units)
    return res, fit_quality(Building("", poly, ground_z, roof_z, solids=dict(res.solids)), pts, frame, units)


def rasterize_model(r: Run) -> None:
    """The city model rendered back into a DSM over the DTM, and how much of each cell its
    roofs cover: tile by tile, each from the buildings that reach into it."""
    from recon3d.quality.rasterize import model_tags, ray_top

    g, dtm, city = r.grid, r.terrain.dtm, r.city
    solids = [b for b in city if b.solids]
    r.quality.model_top = top = ray_top(CityModel(solids, city.crs, city.frame))
    args = []
    for tile in g.tiles:
        near = _touching(solids, g.spec.bounds(tile.rows, tile.cols), margin=g.transform.a)
        args.append((dtm.window(tile.rows, tile.cols), CityModel(near, city.crs, city.frame), top))
    paths = r.tiles("model_dsm", passes.model_dsm, args)
    r.quality.model_dsm = dtm.like(r.grids(g.place(paths, "model", np.float32)), **model_tags())  # float32 tiles
    r.quality.roof_cover = r.grids(g.place(paths, "cover", np.float32, 0.0))  # k / samples**2: 1 stays exactly 1


def _touching(buildings: list[Building], box: tuple, *, margin: float = 0.0) -> list[Building]:
    """The buildings whose footprints reach into ``box`` (xmin, ymin, xmax, ymax) widened by ``margin``."""
    if not buildings:
        return []
    import shapely

    reach = _reaching(shapely.bounds([b.footprint for b in buildings]), box, margin=margin)  # one call: tiles x buildings
    return [b for b, near in zip(buildings, reach, strict=True) if near]


def _reaching(bounds: np.ndarray, box: tuple, *, margin: float = 0.0) -> np.ndarray:
    """(n,) bool: which of the (n, 4) bounds (xmin, ymin, xmax, ymax) reach into ``box`` widened by ``margin``."""
    x0, y0, x1, y1 = box
    lo_x, lo_y, hi_x, hi_y = np.asarray(bounds, np.float64).reshape(-1, 4).T
    return (lo_x <= x1 + margin) & (hi_x >= x0 - margin) & (lo_y <= y1 + margin) & (hi_y >= y0 - margin)


#: Height (m) below the highest surface on the same image ray still counted as seen in an orthophoto.
ORTHO_TOLERANCE = 0.5

#: Share of the judged area in doubtful regions above which the run warns.
DOUBTFUL_WARN_SHARE = 0.05


def make_orthophotos(r: Run) -> None:
    """Stereo inputs: the true orthophoto on the chosen surface and the image-difference
    map of every matched pair on the DSM, with the areas where the images disagree."""
    if r.stereo is None:
        return
    from recon3d.stereo import ortho

    cfg, u, s = r.config.ortho, r.units, r.source
    dsm, q = r.surface.dsm, r.quality
    if r.stereo == "satellite":
        views = ortho.satellite_views(s.scene, dsm.crs, s.stereo.get("relative_bias_px", (0.0, 0.0)))
        pairs = [(0, 1)]
    else:
        views = s.views if s.views is not None else ortho.frame_views(s.scene)
        names = [v.name for v in views]
        pairs = [tuple(names.index(n) for n in record["images"]) for record in s.stereo["pairs"]]
    gsd = ortho.image_gsd(views, dsm)
    surface = {"dsm": dsm, "dtm": r.terrain.dtm, "model": q.model_dsm}[cfg.surface]
    tolerance = u.height(ORTHO_TOLERANCE)
    on_dsm = ortho.looks_on(dsm, views, gsd, tolerance=tolerance)
    objects = ortho.raised_objects(r.terrain.ndsm, u.height(r.config.buildings.min_height))
    q.ortho = ortho.true_ortho(surface, views, gsd, tolerance=tolerance, looks=on_dsm if cfg.surface == "dsm" else None,
                               objects=objects)
    q.ortho_diff = ortho.ortho_difference(dsm, views, pairs, gsd, tolerance=tolerance, looks=on_dsm)
    ids = [b.id for b in r.city]
    regions = ortho.doubtful_regions(q.ortho_diff, cfg.doubtful_threshold, u.area(cfg.doubtful_area), r.labels, ids)
    judged = np.isfinite(q.ortho_diff.data)
    doubtful = judged & ortho.doubtful_cells(q.ortho_diff, cfg.doubtful_threshold)
    cell = q.ortho.transform.a
    r.auto["ortho"] = {"surface": cfg.surface, "cell": round(cell, 4),
                       "reason": f"the images' ground sample distance ({gsd:.3f}), a whole fraction of the DSM cell"}
    area = sum(reg["area"] for reg in regions)
    r.report["ortho"] = {
        "surface": cfg.surface, "cell": round(cell, 4), "pairs": len(pairs),
        "seen_percent": round(100.0 * float(q.ortho.seen.mean()), 1),
        "judged_percent": round(100.0 * float(judged.mean()), 1),
        "doubtful_percent_of_judged": round(100.0 * float(doubtful.sum() / max(judged.sum(), 1)), 1),
        "threshold": cfg.doubtful_threshold, "doubtful_area": round(area, 1), "regions": regions[:50],
    }
    if judged.any() and area > DOUBTFUL_WARN_SHARE * judged.sum() * dsm.resolution**2:
        r.warn(f"the images disagree on the DSM over {area:.0f} {u.name}2 in {len(regions)} areas "
               f"({100 * area / (judged.sum() * dsm.resolution**2):.1f} % of what they both see with texture): "
               "see ortho_diff.tif and the report's list")
    if cfg.textures:
        on_dtm = cfg.surface == "dtm"  # roofs lean there: they take a true orthophoto on the DSM
        roofs = ortho.true_ortho(dsm, views, gsd, tolerance=tolerance, looks=on_dsm, objects=objects) if on_dtm else q.ortho
        _texture_model(r, views, roofs)


def _texture_model(r: Run, views: list, roofs) -> None:
    """The city model with its roofs textured from the true orthophoto ``roofs`` and its walls from the images."""
    from recon3d.stereo import texture

    q = r.quality
    q.textured = texture.texture_city(r.city, views, roofs, dsm=r.surface.dsm)
    r.report["textures"] = q.textured.info
    for t in q.textured.textures:
        if t.reduced > 1:
            h, w = t.image.shape[:2]
            r.warn(f"{output.Products.GLB_TEXTURED}: the texture from {t.name} is reduced {t.reduced} x to {w} x {h} px, "
                   f"the largest every glTF viewer takes ({texture.MAX_TEXTURE_SIZE} px)")


#: Share (%) of the provider's vegetation points that cloud.laz may call building before
#: the run warns that its buildings contradict the input's classes (the family and the
#: shared tiles measure 0-0.4 %; seed 154, before its crowns were told apart, 34.5 %).
MAX_VEGETATION_AS_BUILDING = 5.0


def evaluate_products(r: Run) -> None:
    """Every point's class (cloud.laz), and the accuracy tables of the products."""
    from recon3d.quality import buildings as building_quality
    from recon3d.quality import evaluate
    from recon3d.quality.rasterize import wall_cells

    u, g, sf, t, q = r.units, r.grid, r.surface, r.terrain, r.quality
    summary = r.source.summary
    tables = []
    reference_grid = None
    if summary.provider_classes:
        reference_grid = building_quality.ReferenceGrid.over(*sf.surface_bounds, u.length(0.25))
    paths = r.passes["finish"] = _finish_pass(r, reference_grid)
    if summary.provider_classes:
        tables.append(_against_provider_classes(r, paths, reference_grid))
    if r.inputs.truth_dsm is not None:
        from recon3d.io.geotiff import read_raster

        truth = read_raster(r.inputs.truth_dsm)
        tables.append(evaluate.against_raster(sf.dsm, truth, product_name="DSM", reference_name="reference DSM", units=u))
        covered = np.isfinite(evaluate.resample_max(truth, sf.dsm))
        # share of the cells the reference covers that the DSM fills
        r.report["dsm_filled_percent"] = round(100.0 * float(np.isfinite(sf.dsm.data[covered]).mean()), 2)
    if r.source.checkpoints is not None:
        products = {"DSM": sf.dsm, "DTM": t.dtm, "model DSM": q.model_dsm}
        tables += evaluate.against_checkpoints(products, r.source.checkpoints, u)
    roofs = sf.dsm.data - q.model_dsm.data
    on_buildings = evaluate.model_check_cells(sf.dsm, q.model_dsm, r.labels, r.evidence.vegetated, sf.filled)
    # cells a wall crosses mix roof and ground, or two roofs: there the difference
    # measures where the wall runs (its own accuracy, planimetric), not the roof's height
    inside_roofs = on_buildings & (q.roof_cover >= 1.0) & ~wall_cells(r.city, sf.dsm)
    # from images the DSM is matched, with errors of its own: the rows say how well the
    # model fits it, and must not read as the model's accuracy (the check points are)
    measured = "matched DSM" if r.stereo else "measured DSM"
    for cells, reference in ((on_buildings, f"{measured} on roofs"), (inside_roofs, f"{measured} inside roofs")):
        tables.append(
            AccuracyReport.from_errors(-roofs[cells], product="model DSM", reference=reference, metres_per_unit=u.vertical)
        )
    # where a cell's points fell decides its height beside walls and on steep roofs;
    # the model scanned at the same points and gridded alike has no such error
    q.model_scan = sf.dsm.like(g.place(paths, "scan"), product="model scanned at the points")  # float32
    scan = q.model_scan.data - sf.dsm.data
    tables.append(
        AccuracyReport.from_errors(
            scan[on_buildings & np.isfinite(scan)], product="model scanned at the points",
            reference=f"{measured} on roofs", metres_per_unit=u.vertical,
        )
    )
    r.report["accuracy"] = [tb.to_dict() for tb in tables]
    rms = evaluate.roof_errors(r.labels, np.where(sf.filled, np.nan, -roofs), len(r.city)) * u.vertical
    for b, value in zip(r.city, rms, strict=True):
        if b.solids and np.isfinite(value):
            b.attributes["roof_rms_m"] = round(float(value), 3)
    statuses = [b.status for b in r.city]
    r.report["buildings"] = {
        "count": len(r.city),
        "with_solid": sum(bool(b.solids) for b in r.city),
        "reasons": {k: sum(b.reason == k for b in r.city) for k in sorted({b.reason for b in r.city if b.reason})},
        "statuses": {k: statuses.count(k) for k in sorted(set(statuses))},
        "lods": {k: sum(k in b.solids for b in r.city) for k in sorted({k for b in r.city for k in b.solids})},
        "blocks": len(r.city.blocks()),  # split at height jumps: Building + BuildingParts
    }


def _finish_pass(r: Run, reference_grid) -> list[Path]:
    """The tiles' last pass (:func:`passes.finish`); what they share is let go with it."""
    shared = _finish_shared(r)
    paths = r.tiles("finish", passes.finish, [(_finish_args(r, tile, shared, reference_grid),) for tile in r.grid.tiles])
    r.executor.close()  # the last pass: the workers' memory back before the evaluation, the products and the report
    return paths


def _against_provider_classes(r: Run, paths: list[Path], reference_grid) -> AccuracyReport:
    """The report's comparisons with the input's own classes (building area, vegetation
    taken for building, buildings found) and the DTM's table at the provider's ground points."""
    from recon3d.quality import buildings as building_quality
    from recon3d.quality import evaluate

    counts = {k: 0 for k in ("vegetation_counts", "coverage_counts")}
    valid_grid = np.zeros(reference_grid.shape, bool)  # each tile's block in place
    ref_grid = np.zeros(reference_grid.shape, bool)
    n_ground = 0
    for path in paths:
        with np.load(path) as data:
            for k in counts:
                counts[k] = counts[k] + data[k]
            r0, r1, c0, c1 = data["reference_window"]
            valid_grid[r0:r1, c0:c1] = data["reference_valid"]
            ref_grid[r0:r1, c0:c1] = data["reference_building"]
            n_ground += int(data["ground_count"])
    area = building_quality.score_against_reference(
        [b.footprint for b in r.city if b.solids], reference_grid, ref_grid, valid_grid, units=r.units)
    del valid_grid, ref_grid
    area.update(building_quality.vegetation_as_building(*(int(v) for v in counts["vegetation_counts"])))
    r.report["buildings_vs_provider_area"] = area
    share = area["vegetation_as_building_percent"]
    if share is not None and share > MAX_VEGETATION_AS_BUILDING:
        r.warn(f"{share:.1f} % of the points the input's own classes call vegetation are building in cloud.laz "
               f"(expected under {MAX_VEGETATION_AS_BUILDING:g} %): trees may have been taken for buildings; "
               "the report's building detection compares both")
    r.report["buildings_vs_provider"] = evaluate.coverage_scores(counts["coverage_counts"])
    # one array of every provider ground point's error, read after the grids are let go;
    # sorted, it is the same whatever the tiling, and so are the sums of the table
    errors, at = np.empty(n_ground, np.float32), 0
    for path in paths:
        with np.load(path) as data:
            part = data["ground_errors"]
            errors[at:at + len(part)] = part
            at += len(part)
    errors.sort()
    return AccuracyReport.from_errors(errors, product="DTM", reference="provider ground points",
                                      metres_per_unit=r.units.vertical)


def _finish_shared(r: Run) -> tuple:
    """What every tile's last pass shares: the buildings with roofs, which labels have a
    solid (and their footprints' bounds), the depth inside the footprints, and where the
    rays start."""
    import shapely

    from recon3d.buildings.classes import footprint_depth
    from recon3d.quality.rasterize import ray_top

    with_roofs = [b for b in r.city if "2.2" in b.solids]
    with_solid = np.array([False] + [bool(b.solids) for b in r.city])
    solid_labels = np.flatnonzero(with_solid)
    solid_bounds = shapely.bounds([r.city.buildings[v - 1].footprint for v in solid_labels])
    depth = footprint_depth(r.labels, r.grid.transform.a)
    roofs = CityModel(with_roofs, r.city.crs, r.city.frame)
    return with_roofs, with_solid, (solid_labels, solid_bounds), depth, ray_top(roofs, "2.2"), r.quality.model_top


def _finish_args(r: Run, tile: Tile, shared: tuple, reference_grid) -> passes.Finish:
    """The rasters and buildings the last pass reads around ``tile``."""
    u, g = r.units, r.grid
    with_roofs, with_solid, (solid_labels, solid_bounds), depth, roofs_top, model_top = shared
    rows, cols = tile.window(1, g.shape)
    box = g.spec.bounds(rows, cols)

    def touching(buildings):
        keep = [b for b in _touching(buildings, box) if b.solids]
        return CityModel(keep, r.city.crs, r.city.frame) if keep else None

    plane = r.evidence.plane_tolerance
    # the buildings with a solid whose footprints reach the window, and their labels:
    # every footprint that holds a point of the tile is among them
    near = solid_labels[_reaching(solid_bounds, box)]
    model = [r.city.buildings[v - 1] for v in near]
    return passes.Finish(
        labels=r.labels[rows, cols], depth=depth[rows, cols],
        dtm=r.terrain.dtm.window(rows, cols), dsm=r.surface.dsm.window(rows, cols), with_solid=with_solid,
        roofs=touching(with_roofs) if with_roofs else None,
        model=CityModel(model, r.city.crs, r.city.frame) if model else None, roofs_top=roofs_top, model_top=model_top,
        tolerance=max(u.height(0.25), 2.0 * plane), plane_tolerance=plane,
        hidden_ground=bool(r.auto.get("dsm.hidden_ground", {}).get("value")), reference_grid=reference_grid,
        buffer=g.buffers["reference"], crowns=None if r.evidence.crowns is None else r.evidence.crowns[rows, cols],
        sunk=None if r.terrain.sunk is None else r.terrain.sunk[rows, cols],
        outlines=(near, [b.footprint for b in model]),
    )


def detect_changes(r: Run) -> None:
    """Compare the older building database, when one was given, with the new model."""
    if r.source.old_buildings is None:
        return
    from recon3d.quality import change

    cfg, t, g = r.config.change, r.terrain, r.grid
    q = r.quality
    q.changes = change.detect_changes(
        r.source.old_buildings, r.city, t.ndsm, units=r.units,
        config=change.ChangeParams(height_field=cfg.height_field, height_reference=cfg.height_reference),
        vegetation=t.ndsm.like(r.evidence.vegetated.astype(np.float32)),
        density=t.ndsm.like(g.place(r.passes["surface"], "points", np.float32, 0.0) / g.transform.a**2,
                            product="point density"),
    )
    for message in q.changes.warnings:
        r.warn(message)
    r.report["changes"] = {"summary": q.changes.summary, "notes": q.changes.notes, "warnings": q.changes.warnings}


def write_products(r: Run) -> None:
    """Every product into the work folder (published whole at the end)."""
    from recon3d.pipeline.products import write_products as write

    write(r)


STAGES: list[tuple[str, Callable[[Run], None]]] = [
    ("read", read_inputs),
    ("stereo", match_stereo),
    ("tiles", plan),
    ("dsm", make_dsm),
    ("ground", classify_ground),
    ("dtm", make_dtm),
    ("vegetation", classify_vegetation),
    ("buildings", find_buildings),
    ("lod", build_solids),
    ("model_dsm", rasterize_model),
    ("ortho", make_orthophotos),
    ("evaluate", evaluate_products),
    ("change", detect_changes),
    ("write", write_products),
]


def _result(r: Run) -> RunResult:
    """What the caller gets back; the per-point arrays only with ``keep_points``."""
    sf, t, q = r.surface, r.terrain, r.quality
    out = RunResult(
        out_dir=r.out_dir, input_path=r.inputs.input_path, config=r.config, units=r.units, city=r.city, dsm=sf.dsm, dtm=t.dtm, ndsm=t.ndsm,
        model_dsm=q.model_dsm, roof_cover=q.roof_cover, model_scan=q.model_scan, labels=r.labels, auto=r.auto, report=r.report, notes=r.notes,
        warnings=r.warnings, timings=r.timings, scene=r.source.scene, ortho=q.ortho, ortho_diff=q.ortho_diff,
        changes=q.changes, dsm_filled=sf.filled, dsm_unobserved=sf.unobserved, common_area=sf.common_area,
        vegetation_share=r.evidence.share, footprints=r.source.footprints,
    )
    keep = r.keep_points if r.keep_points is not None else r.source.summary.count <= KEEP_POINTS
    if keep:
        _points_of(r, out)
    return out


#: Points up to which :func:`run` returns the per-point arrays unless told otherwise.
KEEP_POINTS = 2_000_000


def _points_of(r: Run, out: RunResult) -> None:
    """The whole cloud and its per-point results, in the survey's order."""
    g = r.grid
    parts = [g.spec.core(tile) for tile in g.tiles]
    order = np.concatenate([p.order for p in parts])
    sort = np.argsort(order, kind="stable")

    def joined(name: str, key: str) -> np.ndarray:
        return np.concatenate([passes.load(g.spec, tile, name)[key] for tile in g.tiles])[sort]

    xyz = np.concatenate([p.cloud.xyz for p in parts])[sort]
    names = list(parts[0].cloud.attributes)
    attrs = {k: np.concatenate([p.cloud.attributes[k] for p in parts])[sort] for k in names}
    out.cloud = PointCloud(xyz, attrs, r.source.crs)
    out.is_ground = joined("ground", "is_ground")
    out.vegetation = joined("vegetation_decide", "vegetation")
    out.roughness = joined("vegetation_decide", "roughness")
    out.point_classes = joined("finish", "classes")
    out.reference_classes = attrs.get("classification") if r.source.summary.provider_classes else None
