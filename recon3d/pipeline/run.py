"""``recon3d run``: the stage table, the output folder and run.json.

This is the only module that knows file names, the order of stages and the output
folder. Every stage is a small function reading and extending one :class:`RunState`.
The whole output folder is written under a temporary name beside the target and
renamed at the end, so a failed run leaves nothing behind and an existing folder is
replaced only with ``overwrite=True``.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyproj

from recon3d import __version__
from recon3d.buildings import align, blocks, classes, detect, lod, vegetation
from recon3d.buildings.measure import measure_heights
from recon3d.config import PipelineConfig
from recon3d.core.city import Building, CityModel
from recon3d.core.geo import CRSIdentification, LocalFrame, Units, crs_name, crs_units, identify_crs
from recon3d.core.memory import require_memory
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster
from recon3d.errors import InputError
from recon3d.io import checkpoints as checkpoints_io
from recon3d.io import vectors
from recon3d.io.geotiff import write_raster
from recon3d.io.las import las_date, las_tiles, read_las, read_las_tiles, write_las
from recon3d.pipeline import output
from recon3d.pipeline.executor import default_workers, map_ordered
from recon3d.quality import evaluate
from recon3d.quality.rasterize import render, surface_at
from recon3d.terrain import dsm as dsm_stage
from recon3d.terrain import dtm as dtm_stage
from recon3d.terrain import ground as ground_stage

log = logging.getLogger(__name__)

__all__ = ["RunState", "model_check_cells", "model_scan", "run"]

ProgressCallback = Callable[[str, int, int], None]


@dataclass
class RunState:
    """Everything one run reads, chooses and produces; stages fill it in order."""

    input_path: Path
    out_dir: Path
    work_dir: Path
    config: PipelineConfig
    crs: pyproj.CRS | None = None
    footprints_path: Path | None = None
    checkpoints_path: Path | None = None
    breaklines_path: Path | None = None
    altimetry_path: Path | None = None
    dem_path: Path | None = None
    truth_dsm_path: Path | None = None
    old_buildings_path: Path | None = None
    gcps_path: Path | None = None
    workers: int | None = 1  # processes building solids; None: chosen by build_solids
    progress: Callable[[str], None] | None = None  # reports progress within the running stage
    gcps: Any = None
    old_buildings: list | None = None
    changes: Any = None
    constraints: np.ndarray | None = None
    dem: Raster | None = None
    vectors_read: bool = False
    scene: Any = None
    satellite_paths: tuple[Path, Path] | None = None
    tile_paths: list[Path] | None = None  # LAS/LAZ tiles of one survey, read as one cloud
    cloud: PointCloud | None = None
    units: Units | None = None
    crs_identification: CRSIdentification | None = None  # the EPSG code found for the cloud's CRS
    footprints: list[vectors.Footprint] | None = None
    checkpoints: checkpoints_io.CheckPoints | None = None
    reference_classes: np.ndarray | None = None
    dsm: Raster | None = None
    dsm_unobserved: np.ndarray | None = None  # stereo: DSM cells holding no observed point
    common_area: np.ndarray | None = None  # frame stereo: DSM cells two matched images both see
    dsm_extent: tuple | None = None  # the DSM grid's area when not the cloud's bounds
    dsm_consistent: np.ndarray | None = None  # stereo: DSM cells holding a guess the images agree with
    reference_date: str | None = None  # of the input data (LAS header), ISO
    dsm_filled: np.ndarray | None = None  # DSM cells holding no point at all, filled from their rim
    views: list | None = None  # frame stereo: the images and their projections (recon3d.stereo.ortho.View)
    ortho: Any = None  # stereo: the true orthophoto (recon3d.stereo.ortho.OrthoImage)
    ortho_diff: Raster | None = None  # stereo: image difference of the matched pairs on the DSM
    dtm: Raster | None = None
    ndsm: Raster | None = None
    model_dsm: Raster | None = None
    roof_cover: np.ndarray | None = None  # share of each cell under the model's roofs (1 = wholly)
    is_ground: np.ndarray | None = None
    vegetation: np.ndarray | None = None
    vegetation_share: np.ndarray | None = None
    roughness: np.ndarray | None = None
    plane_tolerance: float = 0.0
    point_classes: np.ndarray | None = None
    dtm_points: np.ndarray | None = None
    city: CityModel | None = None
    labels: np.ndarray | None = None
    auto: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    report: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)

    def warn(self, message: str) -> None:
        """A warning the user must see: logged (the terminal), kept for run.json and the report."""
        log.warning("%s", message)
        self.warnings.append(message)


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
) -> RunState:
    """Run the point-cloud pipeline and write the output folder.

    Parameters
    ----------
    input_path : path-like or sequence of path-likes
        LAS/LAZ or PLY point cloud, LAS/LAZ tiles of one survey (files, a folder of
        them or a glob pattern; read as one cloud), a frame-stereo scene folder, or
        two GeoTIFFs with RPCs (satellite stereo).
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
        Processes building the solids, one building at a time each; None uses every
        CPU this process may use from 32 buildings on (the CLI's default). The output
        does not depend on it. With more than one, the worker processes import the
        calling script again, as ``multiprocessing`` does: its top-level code must sit
        under ``if __name__ == "__main__":``.
    progress : callable, optional
        Called as ``progress(stage_name, index, total)`` before each stage, and with
        ``stage_name`` followed by a count (``"lod 40/133"``) during long stages.

    Raises
    ------
    InputError
        Bad input or an existing output folder; nothing is written then.
    """
    pair = None
    items = list(input_path) if isinstance(input_path, tuple | list) else [input_path]
    tiles = las_tiles(items)
    if tiles is not None:
        input_path = tiles[0]
        tiles = tiles if len(tiles) > 1 else None
    elif len(items) == 1:
        input_path = items[0]
    elif len(items) == 2:
        pair = tuple(Path(p) for p in items)
        input_path = pair[0]
    else:
        raise InputError(f"expected one input, LAS/LAZ tiles or two satellite images, got {len(items)} inputs")
    given = [input_path, *(pair or ()), *(tiles or ()), footprints, checkpoints, breaklines, altimetry, dem, truth_dsm,
             old_buildings, gcps]
    out_dir = output.check_output(Path(out_dir), [Path(p) for p in given if p], overwrite=overwrite)
    stale = output.remove_stale(out_dir)
    created = [p for p in (out_dir.parent, *out_dir.parent.parents) if not p.exists()]  # deepest first
    work_dir = output.work_folder(out_dir)
    state = RunState(
        input_path=Path(input_path),
        satellite_paths=pair,
        tile_paths=tiles,
        out_dir=out_dir,
        work_dir=work_dir,
        config=config or PipelineConfig(),
        crs=crs,
        footprints_path=Path(footprints) if footprints else None,
        checkpoints_path=Path(checkpoints) if checkpoints else None,
        breaklines_path=Path(breaklines) if breaklines else None,
        altimetry_path=Path(altimetry) if altimetry else None,
        dem_path=Path(dem) if dem else None,
        truth_dsm_path=Path(truth_dsm) if truth_dsm else None,
        old_buildings_path=Path(old_buildings) if old_buildings else None,
        gcps_path=Path(gcps) if gcps else None,
        workers=workers,
    )
    state.notes += stale
    try:
        for index, (name, stage) in enumerate(STAGES):
            if progress:
                progress(name, index, len(STAGES))
                state.progress = lambda detail, n=name, i=index: progress(f"{n} {detail}", i, len(STAGES))
            start = time.perf_counter()
            stage(state)
            state.timings[name] = round(time.perf_counter() - start, 3)
            log.info("stage %s done in %.2f s", name, state.timings[name])
        _write_json(work_dir / "run.json", _run_record(state))
        from recon3d.report import write_report

        write_report(work_dir)
        output.publish(work_dir, out_dir)
    except BaseException:
        shutil.rmtree(work_dir, ignore_errors=True)  # before its parents can go
        for folder in created:  # a failed run leaves nothing, not even the folders it made
            try:
                folder.rmdir()
            except OSError:
                break
        raise
    finally:
        shutil.rmtree(work_dir, ignore_errors=True)
    return state


# --------------------------------------------------------------------------- stages


def read_inputs(s: RunState) -> None:
    """Read and check every input before anything is computed.

    A point cloud is read whole; a stereo scene folder has its model and images
    checked here and is matched by the next stage.
    """
    from recon3d.io.colmap import is_scene_folder, read_scene

    suffix = s.input_path.suffix.lower()
    if s.satellite_paths is not None:
        from recon3d.io.rpc import read_rpc_camera

        s.scene = [read_rpc_camera(p) for p in s.satellite_paths]
        if s.gcps_path:
            s.gcps = checkpoints_io.read_checkpoints(s.gcps_path)
    elif is_scene_folder(s.input_path):
        s.scene = read_scene(s.input_path, crs=s.crs)
        s.units = crs_units(s.scene.crs, source=str(s.input_path))
        world = s.scene.sparse + s.scene.offset
        _read_vectors(s, s.scene.crs, (world.min(axis=0), world.max(axis=0)))  # before matching, which uses them
    elif s.tile_paths:
        s.cloud, repeats = read_las_tiles(s.tile_paths, crs=s.crs)
        if repeats:
            s.warn(f"{repeats} points are in two overlapping tiles (same x, y, z and GPS time); each is kept once")
        dates = [d for d in map(las_date, s.tile_paths) if d]
        if dates:
            s.reference_date = max(dates)
            s.auto["reference_date"] = {"value": s.reference_date,
                                        "reason": f"latest LAS header creation date of the {len(s.tile_paths)} tiles"}
    elif suffix in (".las", ".laz"):
        s.cloud = read_las(s.input_path, crs=s.crs)
        s.reference_date = las_date(s.input_path)
        if s.reference_date:
            s.auto["reference_date"] = {"value": s.reference_date, "reason": "LAS header creation date"}
    elif suffix == ".ply":
        from recon3d.io.ply import read_ply

        s.cloud = read_ply(s.input_path, crs=s.crs)
    elif not s.input_path.exists():
        raise InputError(f"{s.input_path}: input not found")
    else:
        raise InputError(
            f"{s.input_path}: unsupported input (expected .las, .laz, .ply or a folder with images/ and sparse/)"
        )
    if s.dem_path and s.scene is None:
        raise InputError(f"{s.dem_path}: --dem bounds the matching of a stereo input; {s.input_path} is not one")
    if s.dem_path and s.satellite_paths is not None:
        s.dem = _read_satellite_dem(s.dem_path, s.scene[0])
    if s.cloud is not None:
        _read_side_inputs(s)


def match_stereo(s: RunState) -> None:
    """Dense matching of a scene folder or an RPC pair into the point cloud (nothing to do for clouds)."""
    if s.scene is None:
        return
    if s.satellite_paths is not None:
        s.cloud, s.auto["stereo"] = _satellite_cloud(s)
    else:
        from recon3d.pipeline.stereo import dense_cloud, matching_constraints

        bounds = matching_constraints(
            s.scene, s.config.stereo, s.units, dem=s.dem, footprints=s.footprints, constraints=s.constraints,
        )
        s.cloud, s.auto["stereo"] = dense_cloud(
            s.scene, s.config.stereo, bounds=bounds, warn=s.warn, progress=s.progress,
        )
    _read_side_inputs(s)


#: Least share (percent) of the pixels both satellite images see that must be matched
#: (not filled in) without a warning.
MIN_SATELLITE_MATCHED = 80.0

#: Metres the tallest object may stand above a ``--dem`` of a satellite pair when
#: ``stereo.max_object_height`` is not set (the DEM's own error is ``stereo.dem_tolerance``).
SATELLITE_OBJECT_HEIGHT = 50.0


def _read_satellite_dem(path: Path, cam) -> Raster:
    """The ``--dem`` of a satellite pair, in its own CRS, checked to cover the reference image."""
    from recon3d.io.geotiff import read_raster

    dem = read_raster(path)
    if dem.crs is None:
        raise InputError(f"{path}: the elevation model has no CRS")
    rows = np.array([0.0, 0.0, cam.height - 1.0, cam.height - 1.0, cam.height / 2])
    cols = np.array([0.0, cam.width - 1.0, 0.0, cam.width - 1.0, cam.width / 2])
    lon, lat = cam.localize(rows, cols, np.full(5, float(np.mean(cam.model.height_range))))
    x, y = pyproj.Transformer.from_crs(4326, dem.crs, always_xy=True).transform(lon, lat)
    if not np.isfinite(dem.sample(x, y)).any():
        raise InputError(f"{path}: the elevation model does not cover {cam.image_path} (in its CRS {crs_name(dem.crs)})")
    return dem


def _satellite_cloud(s: RunState) -> tuple[PointCloud, dict]:
    """RPC pair to a cloud in the scene's UTM zone (or the CRS given with --crs)."""
    import rasterio

    from recon3d.stereo.satellite import dense_cloud_rpc

    a, b = s.scene
    images = []
    for cam in (a, b):
        with rasterio.open(cam.image_path) as src:
            images.append(src.read(1, masked=True).astype(np.float32).filled(np.nan))
    cfg = s.config.stereo
    cloud, report = dense_cloud_rpc(
        a, b, *images, tile_size=cfg.tile_size, engine=cfg.engine, dem=s.dem,
        dem_tolerance=cfg.dem_tolerance + (cfg.max_object_height or SATELLITE_OBJECT_HEIGHT), progress=s.progress,
    )
    if report.get("self_check_warning"):
        s.warn(report["self_check_warning"])
    for f in report["tiles"]["failures"]:
        s.warn(f"satellite tile {f['tile']} (pixels {f['core']} of {a.image_path.name}) failed: {f['reason']}")
    if report["matched_percent"] < MIN_SATELLITE_MATCHED:
        s.warn(f"only {report['matched_percent']:.0f} % of the pixels both images see were matched "
               f"(expected >= {MIN_SATELLITE_MATCHED:.0f} %); the rest is filled in and left out of the DTM and buildings")
    report["crs"] = {"value": crs_name(cloud.crs), "reason": "UTM zone of the scene centre"}
    if s.crs is not None:
        t = pyproj.Transformer.from_crs(cloud.crs, s.crs, always_xy=True)
        x, y = t.transform(cloud.xyz[:, 0], cloud.xyz[:, 1])
        cloud = PointCloud(np.column_stack([x, y, cloud.xyz[:, 2]]), cloud.attributes, s.crs)
        report["crs"] = {"value": crs_name(s.crs), "reason": "--crs"}
    if s.gcps is not None:
        from recon3d.stereo.satellite import absolute_shift

        shift, report["absolute_bias"] = absolute_shift(cloud, s.gcps.xyz)
        cloud = PointCloud(cloud.xyz + shift, cloud.attributes, cloud.crs)
    return cloud, report


#: Fewest points a run works with: fewer make no DSM worth the name, let alone buildings.
MIN_POINTS = 100

#: Metres from the cloud's median height beyond which a point is a gross error
#: (no terrain or building spans 10 km vertically): dropped, with a warning.
GROSS_HEIGHT_ERROR = 1e4

#: Largest magnitude of heights (m): beyond it float32 rasters no longer hold
#: centimetres (their step at 131 km is 1.6 cm), and a wrong vertical offset or unit is
#: far more likely than real data.
MAX_ABS_HEIGHT = 1e5


def _check_cloud(s: RunState) -> None:
    """Physical sanity of the cloud: enough points, an area, plausible heights."""
    n = len(s.cloud)
    if n < MIN_POINTS:
        raise InputError(f"{s.input_path}: {n} points: too few for a DSM and buildings (at least {MIN_POINTS})")
    z = s.cloud.xyz[:, 2]
    median = float(np.median(z))
    gross = np.abs(z - median) > s.units.height(GROSS_HEIGHT_ERROR)
    if gross.any():
        s.warn(f"{int(gross.sum())} points lie more than {GROSS_HEIGHT_ERROR:g} m from the median height "
               f"{median:.1f}: gross errors, left out")
        s.cloud = s.cloud[~gross]
    if abs(median) * s.units.vertical > MAX_ABS_HEIGHT:
        raise InputError(
            f"{s.input_path}: heights around {median:.6g} {s.units.name}: rasters cannot hold them to the "
            "centimetre; is the vertical offset or unit wrong?"
        )
    extent = np.ptp(s.cloud.xyz[:, :2], axis=0)
    if extent.min() < s.units.length(2.0):
        raise InputError(
            f"{s.input_path}: the points span {extent[0]:.3g} x {extent[1]:.3g} {s.units.name}: no area to grid"
        )


def _read_side_inputs(s: RunState) -> None:
    """Footprints, check points and terrain constraints, once the cloud and its CRS exist."""
    _identify_crs(s)
    s.units = crs_units(s.cloud.crs, source=str(s.input_path))
    _check_cloud(s)
    if s.cloud.has_classes():
        s.reference_classes = s.cloud.classification.copy()
    if not s.vectors_read:  # frame stereo read them before matching
        _read_vectors(s, s.cloud.crs, s.cloud.bounds)
    s.work_dir.mkdir(parents=True, exist_ok=True)


def _identify_crs(s: RunState) -> None:
    """Find the EPSG code of the cloud's CRS (an ESRI WKT often has one) and write every
    product in its EPSG definition, so each format can name it; warn when none is found."""
    s.crs_identification = identify_crs(s.cloud.crs)
    s.cloud.crs = s.crs_identification.crs
    for message in s.crs_identification.warnings():
        s.warn(message)


def _read_vectors(s: RunState, crs: pyproj.CRS, bounds: tuple[np.ndarray, np.ndarray]) -> None:
    """Footprints, check points, old buildings, terrain constraints and the DEM, in ``crs``;
    ``bounds`` (lowest, highest corner) is the extent the footprints must overlap."""
    s.vectors_read = True
    if s.footprints_path:
        s.footprints, notes = vectors.read_footprints(s.footprints_path, crs=crs)
        s.notes += notes
        _check_overlap(s, bounds, crs)
    if s.checkpoints_path:
        s.checkpoints = checkpoints_io.read_checkpoints(s.checkpoints_path)
    if s.old_buildings_path:
        s.old_buildings, notes = vectors.read_footprints(s.old_buildings_path, crs=crs)
        s.notes += notes
    s.constraints = _read_constraints(s, crs)
    if s.dem_path and s.dem is None:
        from recon3d.io.geotiff import read_dem

        s.dem = read_dem(s.dem_path, crs=crs, bounds=bounds)


def _grid_dsm(s: RunState, cloud: PointCloud, res: float, *, max_hole_cells: int, area=None, extent=None) -> Raster:
    """The DSM of ``cloud`` (the run's cloud, or one with the same points and other
    heights) gridded the way this run grids its DSM."""
    stereo = s.scene is not None  # frame or satellite stereo
    a = cloud.attributes
    observed = a["observed"] > 0 if stereo and "observed" in a else None
    return dsm_stage.make_dsm(
        cloud, res, max_hole_cells=max_hole_cells, rim="low" if stereo else "mean",
        observed=observed, source=a.get("point_source_id") if observed is not None else None, area=area,
        extent=extent, per_source="median" if s.satellite_paths else "max",
    )


#: Largest DSM hole filled (m2) when ``dsm.max_hole_area`` is unset, by source, and the reason run.json records.
HOLE_AREA = {
    "frame": (1000.0, "frame stereo: ground hidden behind buildings from one image (a wide-base survey "
                      "hides whole streets), inside the area both images see, filled from the low side of its rim"),
    "satellite": (200.0, "satellite stereo: ground hidden behind buildings, filled from the low side of its rim"),
    "lidar": (25.0, "LiDAR: gaps between scan lines, filled from the mean of their rim"),
}


def make_dsm(s: RunState) -> None:
    cfg, u = s.config.dsm, s.units
    spacing = dsm_stage.point_spacing(s.cloud.xyz[:, :2])
    gsd = s.auto.get("stereo", {}).get("ground_sample_distance")
    if cfg.resolution:
        res, why = u.length(cfg.resolution), "config"
    elif gsd and spacing < gsd:  # pairs over the same ground add points, not detail
        res, why = dsm_stage.choose_resolution(gsd, u)
        why = why.replace("mean point spacing", "stereo: ground sample distance (the points are denser)")
    else:
        res, why = dsm_stage.choose_resolution(spacing, u)
    s.auto["dsm.resolution"] = {"value": res, "unit": u.name, "reason": why}
    s.auto["point_spacing"] = {"value": round(spacing, 3), "unit": u.name}
    frame_stereo = s.scene is not None and s.satellite_paths is None
    defaults = HOLE_AREA["frame" if frame_stereo else "satellite" if s.scene is not None else "lidar"]
    hole_area = cfg.max_hole_area if cfg.max_hole_area is not None else defaults[0]
    s.auto["dsm.max_hole_area"] = {"value": hole_area, "reason": "config" if cfg.max_hole_area is not None else defaults[1]}

    def common_area(raw: Raster) -> np.ndarray:
        s.common_area = _common_area(s, raw)
        return s.common_area & ~_holes_both_saw(s, raw, s.common_area, int(u.area(SEEN_HOLE_AREA) / res**2))

    # frame stereo: the grid spans the sparse points too, so a part of the common area the
    # matching lost shows as empty cells rather than as a smaller grid
    extent = None
    if frame_stereo:
        world = s.scene.sparse + s.scene.offset
        extent = (np.minimum(s.cloud.bounds[0], world.min(axis=0)), np.maximum(s.cloud.bounds[1], world.max(axis=0)))
    s.dsm_extent = extent
    _check_grid_memory(s, extent or s.cloud.bounds, res)
    s.dsm = _grid_dsm(s, s.cloud, res, max_hole_cells=int(u.area(hole_area) / res**2),
                      area=common_area if frame_stereo else None, extent=extent)
    surface = dsm_stage.surface_points(s.cloud)
    gridded = s.cloud.xyz if surface.all() else s.cloud.xyz[surface]
    count = dsm_stage.grid_points(gridded, s.dsm.transform, s.dsm.shape, reducer="count")
    s.dsm_filled = (count == 0) & np.isfinite(s.dsm.data)
    observed = s.cloud.attributes.get("observed")
    if observed is not None and not observed.all():
        count = dsm_stage.grid_points(s.cloud.xyz[observed > 0], s.dsm.transform, s.dsm.shape, reducer="count")
        s.dsm_unobserved = (count == 0) & np.isfinite(s.dsm.data)
        consistent = s.cloud.attributes.get("consistent")
        if consistent is not None:
            count = dsm_stage.grid_points(s.cloud.xyz[consistent > 0], s.dsm.transform, s.dsm.shape, reducer="count")
            s.dsm_consistent = count > 0
    if s.satellite_paths is not None:  # products only where both images see the ground
        s.common_area = _rpc_common_area(s, s.dsm)
        s.dsm.data[~s.common_area] = np.nan
        s.dsm_filled &= s.common_area
        if s.dsm_unobserved is not None:
            s.dsm_unobserved &= s.common_area
    if frame_stereo and s.common_area is not None:
        _check_common_area(s)


#: Bytes per DSM cell the raster stages hold at their peak (DSM, DTM, nDSM, masks,
#: filters' working copies: about twenty float64 grids).
GRID_BYTES_PER_CELL = 160


def _check_grid_memory(s: RunState, extent, res: float) -> None:
    """Refuse a product grid that would not fit in the memory available, before allocating it."""
    lo, hi = (np.asarray(v, np.float64) for v in extent)
    cells = float(np.ceil((hi[0] - lo[0]) / res + 1) * np.ceil((hi[1] - lo[1]) / res + 1))
    require_memory(cells * GRID_BYTES_PER_CELL, f"a DSM of {cells:.3g} cells of {res:g} {s.units.name}",
                   "choose coarser cells (--set dsm.resolution=...) or cut the input into tiles", source=s.input_path)


#: Largest hole (m2) of a frame-stereo DSM filled although tie points seen by both
#: images of a pair lie in it (see :func:`_holes_both_saw`).
SEEN_HOLE_AREA = 200.0


def _holes_both_saw(s: RunState, raw: Raster, area: np.ndarray, max_cells: int) -> np.ndarray:
    """(rows, cols) bool: the empty regions of ``raw`` in ``area``, larger than
    ``max_cells``, holding two or more of the model's sparse points that both images of
    a matched pair observed.

    Ground hidden from one image behind a building holds no such tie point (one image
    cannot see it); an empty region that does is ground both images saw and the
    matching lost, and it is left empty (and warned of) rather than filled from its rim.
    """
    from scipy import ndimage

    names = [c.name for c in s.scene.cameras]
    both = np.zeros(len(s.scene.sparse), bool)
    for record in s.auto["stereo"]["pairs"]:
        a, b = (names.index(n) for n in record["images"])
        both |= s.scene.seen[a] & s.scene.seen[b]
    holes, n = ndimage.label(~np.isfinite(raw.data) & area)
    if n == 0:
        return np.zeros(area.shape, bool)
    world = s.scene.sparse[both] + s.scene.offset
    ties = dsm_stage.grid_points(world, raw.transform, raw.shape, reducer="count")
    per_hole = np.bincount(holes.ravel(), weights=np.nan_to_num(ties).ravel(), minlength=n + 1)
    size = np.bincount(holes.ravel(), minlength=n + 1)
    seen = (per_hole >= 2) & (size > max_cells)
    seen[0] = False
    return seen[holes]


#: Least share (percent) of the area two images both see that a frame-stereo DSM must
#: fill without a warning.
MIN_COMMON_FILLED = 95.0


#: Pixels along the image borders left out of the common area: their matches are the
#: least sure, and a hole there is better left empty than filled from the wrong side.
COMMON_AREA_MARGIN_PX = 2.0


def _common_area(s: RunState, dsm: Raster) -> np.ndarray:
    """Frame stereo: (rows, cols) bool, the cells both images of a matched pair see.

    A cell is in the common area when its centre lies inside both images of a pair that
    was matched, :data:`COMMON_AREA_MARGIN_PX` or more from their borders (through the
    lens, as the photos were taken), at its own height; without a height, the median.
    A cell holding no matched point must also lie inside them at the height of the
    highest surface within 10 m, so that ground beside a roof the image border cuts is
    not taken for ground in view. (Asking it of every cell lost a third of the common
    area of a wide-angle survey: near the borders, 12 m of height moves a point out of
    the frame; a matched cell is in view whatever its neighbours.)
    """
    from scipy import ndimage

    cameras = {c.name: c for c in s.scene.cameras}
    xs, ys = dsm.cell_centers()
    x, y = np.meshgrid(xs, ys)
    finite = np.isfinite(dsm.data)
    median = float(np.nanmedian(dsm.data)) if finite.any() else 0.0
    own = np.where(finite, dsm.data, median)
    size = 2 * int(np.ceil(s.units.length(10.0) / dsm.resolution)) + 1
    high = ndimage.maximum_filter(np.where(finite, dsm.data, -np.inf), size=size)
    high = np.where(np.isfinite(high), np.maximum(high, own), own)
    matched = s.cloud.xyz[s.cloud.attributes["observed"] > 0] if "observed" in s.cloud.attributes else s.cloud.xyz
    observed = (dsm_stage.grid_points(matched, dsm.transform, dsm.shape, reducer="count") > 0).ravel()
    offset = np.asarray(s.scene.offset)
    points = [np.column_stack([x.ravel(), y.ravel(), z.ravel()]) - offset for z in (own, high)]

    def in_frame(cam, margin: float = COMMON_AREA_MARGIN_PX):
        lo, hi = margin - 0.5, np.array([cam.width, cam.height]) - 0.5 - margin
        inside = []
        for local in points:
            uv, depth = cam.project(local, distort=True)  # the photo as taken, lens and all
            inside.append((depth > 0) & (uv >= lo).all(axis=1) & (uv <= hi).all(axis=1))
        return inside[0] & (observed | inside[1])

    frames = {name: in_frame(cam) for name, cam in cameras.items()}
    common = np.zeros(len(points[0]), bool)
    for record in s.auto["stereo"]["pairs"]:
        a, b = record["images"]
        common |= frames[a] & frames[b]
    return common.reshape(dsm.shape)


def _rpc_common_area(s: RunState, dsm: Raster) -> np.ndarray:
    """Satellite pair: (rows, cols) bool, the cells whose surface both images show.

    Each cell centre, at its DSM height (the median where it has none), is projected
    through both RPCs (the second with the relative bias removed by matching) and must
    fall on a finite pixel of each image, :data:`COMMON_AREA_MARGIN_PX` or more from
    its borders.
    """
    import rasterio

    xs, ys = dsm.cell_centers()
    x, y = np.meshgrid(xs, ys)
    finite = np.isfinite(dsm.data)
    h = np.where(finite, dsm.data, float(np.nanmedian(dsm.data)) if finite.any() else 0.0).ravel()
    lon, lat = pyproj.Transformer.from_crs(dsm.crs, 4326, always_xy=True).transform(x.ravel(), y.ravel())
    shift = np.asarray(s.auto["stereo"].get("relative_bias_px", [0.0, 0.0]), float)
    common = np.ones(h.shape, bool)
    for cam, extra in zip(s.scene, (np.zeros(2), shift), strict=True):
        row, col = cam.project(lon, lat, h)
        col, row = col + extra[0], row + extra[1]
        m = COMMON_AREA_MARGIN_PX
        inside = (col >= m - 0.5) & (col <= cam.width - 0.5 - m) & (row >= m - 0.5) & (row <= cam.height - 0.5 - m)
        with rasterio.open(cam.image_path) as src:
            nodata = ~src.read_masks(1).astype(bool)
        r, c = np.clip(np.rint(row), 0, cam.height - 1).astype(np.int64), np.clip(np.rint(col), 0, cam.width - 1).astype(np.int64)
        common &= inside & ~nodata[r, c]
    return common.reshape(dsm.shape)


def _check_common_area(s: RunState) -> None:
    """Frame stereo: how much of the common area the DSM fills; a warning below
    :data:`MIN_COMMON_FILLED` percent, naming where the empty cells are."""
    common = s.common_area
    xs, ys = s.dsm.cell_centers()
    x, y = np.meshgrid(xs, ys)
    filled = np.isfinite(s.dsm.data) & common
    observed = filled & ~s.dsm_filled & (~s.dsm_unobserved if s.dsm_unobserved is not None else True)
    n = max(1, int(common.sum()))
    area = {
        "cells": int(common.sum()),
        "area_m2": round(float(common.sum() * (s.dsm.resolution * s.units.horizontal) ** 2), 1),
        "filled_percent": round(100.0 * float(filled.sum()) / n, 2),
        "observed_percent": round(100.0 * float(observed.sum()) / n, 2),
    }
    s.auto["stereo"]["common_area"] = area
    if area["filled_percent"] < MIN_COMMON_FILLED:
        rows, cols = np.nonzero(common & ~filled)
        xs, ys = x[rows, cols], y[rows, cols]
        s.auto["stereo"]["common_area"]["empty_extent"] = [float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())]
        s.warn(
            f"the DSM fills {area['filled_percent']:.0f} % of the {area['area_m2']:.0f} m2 that the matched "
            f"image pairs both see (expected >= {MIN_COMMON_FILLED:.0f} %); {len(rows)} cells are empty, "
            f"within x {xs.min():.0f}..{xs.max():.0f}, y {ys.min():.0f}..{ys.max():.0f}"
        )


def classify_ground(s: RunState) -> None:
    result = ground_stage.classify_ground(s.cloud, s.config.ground, s.units, s.dsm.resolution)
    s.is_ground = result.is_ground
    s.dtm_points = result.for_dtm
    s.auto["ground"] = result.params
    if s.reference_classes is not None:
        s.report["ground_filter"] = evaluate.ground_filter_errors(s.is_ground, s.reference_classes)


def make_dtm(s: RunState) -> None:
    noise = s.auto["ground"].get("noise", {}).get("value", 0.0) / s.units.vertical
    constraints = None
    if s.constraints is not None:
        lines, points = s.constraints
        constraints = np.concatenate([dtm_stage.densify_lines(lines, s.dsm.resolution / 2), points])
    points = s.dtm_points
    if s.satellite_paths is not None and "observed" in s.cloud.attributes:
        points = points & (s.cloud.attributes["observed"] > 0)  # a filled-in disparity is no ground
    s.dtm = dtm_stage.make_dtm(s.cloud.xyz[points], s.dsm, noise=noise, constraints=constraints)
    if s.satellite_paths is not None:  # no extrapolation beyond what both images see
        s.dtm.data[~np.isfinite(s.dsm.data)] = np.nan
    elif s.dsm_unobserved is not None:
        _lower_unseen_guesses(s, noise)
    s.ndsm = dtm_stage.make_ndsm(s.dsm, s.dtm)


def _lower_unseen_guesses(s: RunState, noise: float) -> None:
    """Stereo DSM cells filled in at a height where both images of a matched pair would
    have seen them (and so matched them) are hidden ground: they take the DTM.

    Cells holding no matched point and no guess the images agree with are judged, in
    regions of at least 4 m2: the few cells the matcher misses on a roof or in a crown
    are noise, not hidden ground.
    """
    from scipy import ndimage

    cameras = {c.name: c for c in s.scene.cameras}
    offset = np.asarray(s.scene.offset)
    unjudged = s.dsm_unobserved if s.dsm_consistent is None else s.dsm_unobserved & ~s.dsm_consistent
    regions, n = ndimage.label(unjudged)
    area = ndimage.sum_labels(np.ones(regions.shape), regions, np.arange(1, n + 1)) * s.dsm.resolution**2
    judged = unjudged & (np.r_[0.0, area][regions] >= s.units.area(4.0))
    tolerance = max(s.units.height(0.5), 3.0 * noise)
    seen = np.zeros(judged.shape, bool)
    for record in s.auto["stereo"]["pairs"]:
        pair = [cameras[name] for name in record["images"]]

        def in_frame(i, xyz, pair=pair):
            uv, depth = pair[i].project(xyz - offset, distort=True)
            w, h = pair[i].width, pair[i].height
            return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)

        centres = np.array([c.center for c in pair]) + offset
        seen |= dsm_stage.seen_by_all(s.dsm, judged & ~seen, centres, tolerance=tolerance, in_frame=in_frame)
    lower = seen & (s.dsm.data > s.dtm.data + tolerance)
    s.dsm.data[lower] = s.dtm.data[lower]
    s.auto["dsm.hidden_ground"] = {
        "value": int(lower.sum()),
        "reason": "cells no pixel matched, filled in at a height both images of a pair would have seen: set to the DTM",
    }


def find_buildings(s: RunState) -> None:
    cfg, u = s.config.buildings, s.units
    noise = s.auto["ground"].get("noise", {}).get("value", 0.0) / u.vertical
    s.vegetation, s.roughness = vegetation.classify_vegetation(s.cloud, s.dtm, cfg, u, noise=noise, with_roughness=True)
    share = vegetation.vegetation_cells(s.cloud, s.dsm, s.vegetation, share=True)
    s.plane_tolerance = vegetation.plane_tolerance(cfg, u, noise)
    planar = vegetation.planar_cells(s.cloud, s.dsm, s.roughness, s.plane_tolerance)
    s.vegetation_share = share
    if s.footprints is not None:
        evidence = detect.building_evidence(s.ndsm, share, cfg, u)
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
            s.notes.append(f"{len(no_building)} footprints have no building under them: " + ", ".join(no_building[:20]))
        if len(shifts):
            s.auto["footprint_shift"] = {"value": np.round(np.median(shifts, axis=0), 3).tolist(),
                                         "reason": "median map-to-data shift found by aligning footprints with the nDSM"}
    else:
        ndsm = s.ndsm
        if s.satellite_paths is not None and s.dsm_unobserved is not None:  # only where matched
            ndsm = Raster(np.where(s.dsm_unobserved, np.nan, s.ndsm.data), s.ndsm.transform, s.ndsm.crs, s.ndsm.tags)
        polygons = detect.detect_buildings(
            ndsm, share, cfg, u, cloud=s.cloud, dtm=s.dtm, point_vegetation=s.vegetation, planar=planar,
            point_density=_point_density(s),
        )
        if s.satellite_paths is not None and s.dsm_unobserved is not None:
            polygons = _on_observed_ground(s, polygons)
        ids = [f"b{i + 1:04d}" for i in range(len(polygons))]
        attrs = [{"source": "detected", **_rounded(detect.blob_descriptors(p))} for p in polygons]
        if s.scene is not None and s.satellite_paths is None and cfg.image_outlines and polygons:
            polygons = _outlines_from_images(s, polygons, attrs)
    s.labels = detect.label_footprints(polygons, s.dsm)
    heights = measure_heights(
        polygons, s.labels, s.dsm, s.dtm, percentile=cfg.roof_percentile, min_height=u.height(cfg.min_height)
    )
    buildings = []
    for i, poly in enumerate(polygons):
        attrs[i].update(cells=int(heights.cells[i]), raised_share=round(float(heights.raised_share[i]), 3))
        buildings.append(Building(ids[i], poly, heights.ground_z[i], heights.roof_z[i], attributes=attrs[i]))
    if s.footprints is None:  # parts of a block split at height jumps: Building + BuildingParts
        raised = detect.building_mask(s.ndsm, share, cfg, u)
        blocks.assign_blocks(buildings, s.labels, raised, min_shared=u.length(cfg.min_edge))
    lo = s.cloud.bounds[0]
    # the date of the data, not of the run: the same input gives the same bytes
    meta = {"referenceDate": s.reference_date} if s.reference_date else {}
    s.city = CityModel(buildings, s.cloud.crs, LocalFrame.around(lo, step=u.length(100.0)), meta)


#: Least share of the ring of cells around a detected satellite building (2 to 6 m out)
#: that must hold matched observations: a "building" amid filled-in cells stands on
#: terrain nobody saw.
MIN_OBSERVED_RING = 0.5


def _on_observed_ground(s: RunState, polygons: list) -> list:
    """The detected outlines whose surrounding terrain was observed (see :data:`MIN_OBSERVED_RING`)."""
    from scipy import ndimage

    if not polygons:
        return polygons
    labels = detect.label_footprints(polygons, s.dsm)
    near = int(np.ceil(s.units.length(2.0) / s.dsm.resolution))
    far = int(np.ceil(s.units.length(6.0) / s.dsm.resolution))
    reach = ndimage.grey_dilation(labels, size=2 * far + 1)  # the label of a building within 6 m
    close = ndimage.grey_dilation(labels, size=2 * near + 1) > 0
    ring = (reach > 0) & ~close
    seen = ring & np.isfinite(s.dsm.data) & ~s.dsm_unobserved
    n = len(polygons) + 1
    share = np.bincount(reach[seen], minlength=n) / np.maximum(np.bincount(reach[ring], minlength=n), 1)
    keep = share[1:] >= MIN_OBSERVED_RING
    if not keep.all():
        s.notes.append(f"{int((~keep).sum())} detected buildings dropped: the terrain around them was not matched")
    return [p for p, k in zip(polygons, keep, strict=True) if k]


def _outlines_from_images(s: RunState, polygons: list, attrs: list[dict]) -> list:
    """Frame stereo: the detected outlines moved edge by edge to the eaves two images
    agree on (:mod:`recon3d.buildings.image_outline`); ``outline_source`` says which
    outline each building kept."""
    from recon3d.buildings import image_outline
    from recon3d.stereo import ortho

    if s.views is None:
        s.views = ortho.frame_views(s.scene)
    found = image_outline.refine_outlines(polygons, s.views, s.dsm, metre=s.units.length(1.0))
    for a, r in zip(attrs, found, strict=True):
        a.update(outline_source=r.source, outline_moved_share=round(r.moved_share, 3),
                 outline_shift=round(r.mean_shift, 3))
    moved = sum(r.source == "images" for r in found)
    s.auto["image_outlines"] = {
        "value": moved, "of": len(found),
        "reason": "outlines moved to the eaves where the two most nadir images agree within "
                  f"{image_outline.AGREEMENT} m (set buildings.image_outlines=false to keep the nDSM outlines)",
    }
    return [r.polygon for r in found]


def _rounded(values: dict) -> dict:
    return {k: round(float(v), 3) for k, v in values.items()}


def build_solids(s: RunState) -> None:
    import shapely

    u = s.units
    lo, hi = s.cloud.bounds
    extent = shapely.box(lo[0], lo[1], hi[0], hi[1])
    roof = ~s.is_ground & ~s.vegetation  # points that may lie on roofs
    xyz = s.cloud.xyz[roof]
    order = np.argsort(xyz[:, 0], kind="stable")  # x-sorted once: each building slices its bbox
    xyz, xs = xyz[order], xyz[order, 0]
    jobs, built = [], []
    for b in s.city:
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
        x0, y0, x1, y1 = poly.bounds
        i0, i1 = np.searchsorted(xs, [x0, x1])
        pts = xyz[i0:i1]
        pts = pts[(pts[:, 1] >= y0) & (pts[:, 1] <= y1)]
        jobs.append((poly, pts, b.ground_z, b.roof_z, s.city.frame, s.config.lod, u))
        built.append(b)
    if s.workers:
        workers, why = s.workers, "given (--workers, or run(workers=))"
    elif len(jobs) < _PARALLEL_FROM:
        workers, why = 1, f"fewer than {_PARALLEL_FROM} buildings: starting processes (about 1 s) costs more than it saves"
    else:
        workers, why = default_workers(), "the CPUs this process may use (affinity, container quota)"
    s.auto["workers"] = {"value": min(workers, max(len(jobs), 1)), "reason": why}
    done = None if s.progress is None else lambda k: s.progress(f"{k}/{len(jobs)} buildings")
    from recon3d.quality.roofs import fit_quality, validity_attributes

    results = map_ordered(_build_lods, jobs, workers, done=done)
    empty = dict(zip((b.id for b in s.city), _empty_share(s)[1:], strict=False))
    for b, res, job in zip(built, results, jobs, strict=True):
        b.solids.update(res.solids)
        b.status, b.reason = res.status, res.reason
        b.attributes.update(roof_type=res.roof_type, roof_planes=len(res.planes))
        if np.isfinite(res.roof_rms):
            b.attributes["roof_point_rms_m"] = round(float(res.roof_rms) * u.vertical, 3)
        b.attributes.update(fit_quality(b, job[1], s.city.frame, u, empty.get(b.id, 0.0)))
        b.attributes.update(validity_attributes(res.validity))
    failed = [b.id for b in s.city if not b.solids]
    if failed:
        s.notes.append(f"{len(failed)} footprints got no solid: " + ", ".join(failed[:20]))
    missed = sorted(
        ((b.attributes["roof_unmodelled_area_m2"], b.id) for b in s.city if b.attributes.get("roof_unmodelled_parts")),
        reverse=True,
    )
    if missed:
        s.notes.append(
            f"{len(missed)} buildings have roof parts their model misses ({sum(a for a, _ in missed):.1f} m2 in all; "
            "groups of roof points more than 1 m off, 2 m2 and more: roof_unmodelled_area_m2): "
            + ", ".join(f"{i} {a:.1f} m2" for a, i in missed[:10])
        )


def _empty_share(s: RunState) -> np.ndarray:
    """(buildings + 1,) share of each footprint's DSM cells that hold no point (filled from their rim)."""
    labels = s.labels.ravel()
    n = int(labels.max()) + 1 if labels.size else 1
    cells = np.bincount(labels, minlength=n)
    empty = np.bincount(labels[s.dsm_filled.ravel()], minlength=n) if s.dsm_filled is not None else np.zeros(n)
    return empty / np.maximum(cells, 1)


#: Buildings from which ``build_solids`` uses every CPU by default (a building takes
#: 30 ms at the median, a worker process about 1 s to start and import Open3D).
_PARALLEL_FROM = 32


def _build_lods(job: tuple) -> lod.LodResult:
    """One building's solids (a worker process runs this for :func:`build_solids`)."""
    poly, pts, ground_z, roof_z, frame, config, units = job
    return lod.build_lods(poly, pts, ground_z, roof_z, frame, config, units=units)


def _point_density(s: RunState) -> float:
    """First returns per square metre over the DSM cells that hold data."""
    a = s.cloud.attributes
    first = np.count_nonzero(np.asarray(a["return_number"]) <= 1) if "return_number" in a else len(s.cloud)
    area = np.count_nonzero(np.isfinite(s.dsm.data)) * s.units.area(1.0) ** -1 * s.dsm.resolution**2
    return float(first / area) if area > 0 else 0.0


def _roof_surface(s: RunState) -> np.ndarray | None:
    """(n,) height of the LoD2.2 roofs above each point of the cloud, NaN off them
    (and off buildings that fell back on LoD1: their prisms are no roof surface)."""
    from recon3d.core.city import CityModel
    from recon3d.quality.rasterize import surface_at

    with_roofs = [b for b in s.city if "2.2" in b.solids]
    if not with_roofs or s.roughness is None:
        return None
    xyz = s.cloud.xyz
    inside = np.zeros(len(xyz), bool)
    row, col = s.dsm.rowcol(xyz[:, 0], xyz[:, 1])
    rows, cols = s.dsm.shape
    ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    inside[ok] = s.labels[row[ok], col[ok]] > 0
    out = np.full(len(xyz), np.nan)
    if inside.any():
        model = CityModel(with_roofs, s.city.crs, s.city.frame)
        nowhere = s.dtm.like(np.full(s.dtm.shape, np.nan, np.float32))
        out[inside] = surface_at(model, xyz[inside, 0], xyz[inside, 1], nowhere, lod="2.2")
    return out


def rasterize_model(s: RunState) -> None:
    s.model_dsm, s.roof_cover = render(s.city, s.dtm)


def make_orthophotos(s: RunState) -> None:
    """Stereo inputs: the true orthophoto on the chosen surface and the image-difference
    map of every matched pair on the DSM, with the areas where the images disagree."""
    if s.scene is None:
        return
    from recon3d.stereo import ortho

    cfg, u = s.config.ortho, s.units
    if s.satellite_paths is not None:
        views = ortho.satellite_views(s.scene, s.dsm.crs, s.auto["stereo"].get("relative_bias_px", (0.0, 0.0)))
        pairs = [(0, 1)]
    else:
        views = s.views if s.views is not None else ortho.frame_views(s.scene)
        names = [v.name for v in views]
        pairs = [tuple(names.index(n) for n in record["images"]) for record in s.auto["stereo"]["pairs"]]
    gsd = ortho.image_gsd(views, s.dsm)
    surface = {"dsm": s.dsm, "dtm": s.dtm, "model": s.model_dsm}[cfg.surface]
    tolerance = u.height(ORTHO_TOLERANCE)
    on_dsm = ortho.looks_on(s.dsm, views, gsd, tolerance=tolerance)
    s.ortho = ortho.true_ortho(surface, views, gsd, tolerance=tolerance, looks=on_dsm if cfg.surface == "dsm" else None)
    s.ortho_diff = ortho.ortho_difference(s.dsm, views, pairs, gsd, tolerance=tolerance, looks=on_dsm)
    ids = [b.id for b in s.city]
    regions = ortho.doubtful_regions(s.ortho_diff, cfg.doubtful_threshold, u.area(cfg.doubtful_area), s.labels, ids)
    judged = np.isfinite(s.ortho_diff.data)
    doubtful = judged & ortho.doubtful_cells(s.ortho_diff, cfg.doubtful_threshold)
    cell = s.ortho.transform.a
    s.auto["ortho"] = {"surface": cfg.surface, "cell": round(cell, 4),
                       "reason": f"the images' ground sample distance ({gsd:.3f}), a whole fraction of the DSM cell"}
    area = sum(r["area"] for r in regions)
    s.report["ortho"] = {
        "surface": cfg.surface, "cell": round(cell, 4), "pairs": len(pairs),
        "seen_percent": round(100.0 * float(s.ortho.seen.mean()), 1),
        "judged_percent": round(100.0 * float(judged.mean()), 1),
        "doubtful_percent_of_judged": round(100.0 * float(doubtful.sum() / max(judged.sum(), 1)), 1),
        "threshold": cfg.doubtful_threshold, "doubtful_area": round(area, 1), "regions": regions[:50],
    }
    if judged.any() and area > DOUBTFUL_WARN_SHARE * judged.sum() * s.dsm.resolution**2:
        s.warn(f"the images disagree on the DSM over {area:.0f} {u.name}2 in {len(regions)} areas "
               f"({100 * area / (judged.sum() * s.dsm.resolution**2):.1f} % of what they both see with texture): "
               "see ortho_diff.tif and the report's list")


#: Height (m) below the highest surface on the same image ray still counted as seen in an orthophoto.
ORTHO_TOLERANCE = 0.5

#: Share of the judged area in doubtful regions above which the run warns.
DOUBTFUL_WARN_SHARE = 0.05


def evaluate_products(s: RunState) -> None:
    u = s.units
    tables = []
    with_solid = np.array([False] + [bool(b.solids) for b in s.city])
    s.point_classes = classes.point_classes(
        s.cloud, s.is_ground, s.labels, s.dsm, s.dtm, s.config.buildings, u, vegetation=s.vegetation, with_solid=with_solid,
        roof_surface=_roof_surface(s), roughness=s.roughness, tolerance=max(u.height(0.25), 2.0 * s.plane_tolerance),
        plane_tolerance=s.plane_tolerance,
    )
    if s.auto.get("dsm.hidden_ground", {}).get("value"):
        # the guesses over hidden ground stay in the cloud, above the DSM that replaced them
        xyz = s.cloud.xyz
        above = xyz[:, 2] > s.dsm.sample(xyz[:, 0], xyz[:, 1], bilinear=False) + u.height(0.5)
        s.point_classes[above] = ASPRS.NOISE
    if s.reference_classes is not None:
        from recon3d.quality import buildings as building_quality

        height = s.cloud.xyz[:, 2] - s.dtm.sample(s.cloud.xyz[:, 0], s.cloud.xyz[:, 1])
        s.report["buildings_vs_provider_area"] = building_quality.evaluate_against_classes(
            [b.footprint for b in s.city if b.solids], s.cloud, s.reference_classes, point_classes=s.point_classes,
            vegetation_truth=building_quality.vegetation_truth_proxy(
                s.cloud, s.reference_classes, height, min_height=u.height(2.5)
            ),
            units=u,
        )
        ref_ground = s.cloud.xyz[s.reference_classes == ASPRS.GROUND]
        tables.append(evaluate.against_points(s.dtm, ref_ground, product="DTM", reference="provider ground points", units=u))
        s.report["buildings_vs_provider"] = evaluate.building_coverage(s.cloud, s.reference_classes, s.labels, s.dsm)
    if s.truth_dsm_path is not None:
        from recon3d.io.geotiff import read_raster

        truth = read_raster(s.truth_dsm_path)
        tables.append(evaluate.against_raster(s.dsm, truth, product_name="DSM", reference_name="reference DSM", units=u))
        covered = np.isfinite(evaluate.resample_max(truth, s.dsm))
        # share of the cells the reference covers that the DSM fills
        s.report["dsm_filled_percent"] = round(100.0 * float(np.isfinite(s.dsm.data[covered]).mean()), 2)
    if s.checkpoints is not None:
        products = {"DSM": s.dsm, "DTM": s.dtm, "model DSM": s.model_dsm}
        tables += evaluate.against_checkpoints(products, s.checkpoints, u)
    roofs = s.dsm.data - s.model_dsm.data
    on_buildings = model_check_cells(s)
    from recon3d.core.accuracy import AccuracyReport

    # cells a wall crosses mix roof and ground: there the difference measures where the
    # outline runs (its own accuracy, planimetric), not the roof's height
    inside_roofs = on_buildings & (s.roof_cover >= 1.0)
    for cells, reference in ((on_buildings, "measured DSM on roofs"), (inside_roofs, "measured DSM inside roofs")):
        tables.append(
            AccuracyReport.from_errors(-roofs[cells], product="model DSM", reference=reference, metres_per_unit=u.vertical)
        )
    # where a cell's points fell decides its height beside walls and on steep roofs;
    # the model scanned at the same points and gridded alike has no such error
    scan = model_scan(s).data - s.dsm.data
    tables.append(
        AccuracyReport.from_errors(
            scan[on_buildings & np.isfinite(scan)], product="model scanned at the points",
            reference="measured DSM on roofs", metres_per_unit=u.vertical,
        )
    )
    s.report["accuracy"] = [t.to_dict() for t in tables]
    _roof_errors(s, np.where(s.dsm_filled, np.nan, -roofs))
    statuses = [b.status for b in s.city]
    s.report["buildings"] = {
        "count": len(s.city),
        "with_solid": sum(bool(b.solids) for b in s.city),
        "reasons": {r: sum(b.reason == r for b in s.city) for r in sorted({b.reason for b in s.city if b.reason})},
        "statuses": {k: statuses.count(k) for k in sorted(set(statuses))},
        "lods": {lod: sum(lod in b.solids for b in s.city) for lod in sorted({k for b in s.city for k in b.solids})},
        "blocks": len(s.city.blocks()),  # split at height jumps: Building + BuildingParts
    }


def model_scan(s: RunState) -> Raster:
    """The DSM a scan of the city model at the cloud's own points would give: each
    point's height replaced by the model's surface above it (the terrain beside the
    buildings), gridded like the measured DSM, without hole filling."""
    xyz = s.cloud.xyz
    z = surface_at(s.city, xyz[:, 0], xyz[:, 1], s.dtm)
    scanned = PointCloud(np.column_stack([xyz[:, :2], z]), s.cloud.attributes, s.cloud.crs)
    extent = s.dsm_extent or s.cloud.bounds  # the measured DSM's grid, even where the model has no surface
    return _grid_dsm(s, scanned[np.isfinite(z)], s.dsm.resolution, max_hole_cells=0, extent=extent)


def model_check_cells(s: RunState) -> np.ndarray:
    """(rows, cols) bool: the building cells on which the model DSM is checked against
    the measured DSM.

    Cells whose top is a tree crown over a roof measure the tree, not the model; cells
    filled from their rim (no point: LiDAR shadow beside walls) measure nothing.
    """
    valid = np.isfinite(s.dsm.data) & np.isfinite(s.model_dsm.data)
    return (s.labels > 0) & valid & ~(np.nan_to_num(s.vegetation_share) > 0.5) & ~s.dsm_filled


def _roof_errors(s: RunState, model_minus_dsm: np.ndarray) -> None:
    """Per building: RMS of model DSM minus measured DSM over its cells (attribute roof_rms_m)."""
    from scipy import ndimage

    labels = np.where(np.isfinite(model_minus_dsm), s.labels, 0)
    index = np.arange(1, len(s.city) + 1)
    sq = np.nan_to_num(model_minus_dsm) ** 2
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(ndimage.mean(sq, labels, index)) * s.units.vertical if len(index) else []
    for b, value in zip(s.city, rms, strict=True):
        if b.solids and np.isfinite(value):
            b.attributes["roof_rms_m"] = round(float(value), 3)


def detect_changes(s: RunState) -> None:
    """Compare the older building database, when one was given, with the new model."""
    if s.old_buildings is None:
        return
    from recon3d.quality import change

    cfg = s.config.change
    s.changes = change.detect_changes(
        s.old_buildings, s.city, s.ndsm, units=s.units,
        config=change.ChangeParams(height_field=cfg.height_field, height_reference=cfg.height_reference),
        vegetation=s.ndsm.like((np.nan_to_num(s.vegetation_share) > 0.5).astype(np.float32)),
        density=change.point_density(s.cloud.xyz, s.ndsm),
    )
    for message in s.changes.warnings:
        s.warn(message)
    s.report["changes"] = {"summary": s.changes.summary, "notes": s.changes.notes, "warnings": s.changes.warnings}


def write_products(s: RunState) -> None:
    from recon3d.io.cityjson import write_cityjson
    from recon3d.io.gltf import write_glb
    from recon3d.io.obj import write_obj
    from recon3d.io.tiles3d import write_3dtiles

    w = s.work_dir
    for name, raster in (("dsm", s.dsm), ("dtm", s.dtm), ("ndsm", s.ndsm), ("model_dsm", s.model_dsm)):
        raster.tags.setdefault("height_units", s.units.name)
        write_raster(raster, w / f"{name}.tif")
    if s.ortho is not None:
        from recon3d.io.geotiff import write_image

        grid = Raster(np.zeros((1, 1)), s.ortho.transform, s.dsm.crs, {"product": f"true orthophoto on the {s.config.ortho.surface}"})
        write_image(s.ortho.data, grid, w / "ortho.tif", mask=s.ortho.seen)
        write_raster(s.ortho_diff, w / "ortho_diff.tif")
    write_las(_classified_cloud(s), w / "cloud.laz")
    write_cityjson(s.city, w / "buildings.city.json")
    write_obj(s.city, w / "buildings.obj")
    write_glb(s.city, w / "buildings.glb")
    write_3dtiles(s.city, w / "buildings_3dtiles")
    _write_footprints(s, w / "footprints.geojson", w / "footprints.gpkg")
    if s.changes is not None:
        from recon3d.quality import change

        geoms, props = change.change_features(s.changes)
        vectors.write_features(w / "changes.geojson", geoms, props, s.city.crs)
        write_raster(change.change_raster(s.changes, s.dsm), w / "changes.tif")
        write_cityjson(change.updated_model(s.old_buildings, s.city, s.changes), w / "buildings_updated.city.json")
    s.report["warnings"] = s.warnings
    _write_json(w / "report.json", s.report)


STAGES: list[tuple[str, Callable[[RunState], None]]] = [
    ("read", read_inputs),
    ("stereo", match_stereo),
    ("dsm", make_dsm),
    ("ground", classify_ground),
    ("dtm", make_dtm),
    ("buildings", find_buildings),
    ("lod", build_solids),
    ("model_dsm", rasterize_model),
    ("ortho", make_orthophotos),
    ("evaluate", evaluate_products),
    ("change", detect_changes),
    ("write", write_products),
]


# --------------------------------------------------------------------------- helpers


def _check_overlap(s: RunState, bounds, crs: pyproj.CRS) -> None:
    lo, hi = bounds
    import shapely

    box = shapely.box(lo[0], lo[1], hi[0], hi[1])
    what = "the point cloud" if s.scene is None else "the scene's sparse points"
    if not any(f.polygon.intersects(box) for f in s.footprints):
        raise InputError(
            f"{s.footprints_path}: none of the {len(s.footprints)} footprints overlaps {what} "
            f"(extent {lo[0]:.1f},{lo[1]:.1f} - {hi[0]:.1f},{hi[1]:.1f} in {crs_name(crs)}); "
            "check the footprints' CRS"
        )


def _read_constraints(s: RunState, crs: pyproj.CRS) -> tuple[list[np.ndarray], np.ndarray] | None:
    """Breaklines and spot heights for the DTM, or None when neither was given."""
    lines, points = [], np.zeros((0, 3))
    if s.breaklines_path:
        lines, more = vectors.read_terrain_vectors(s.breaklines_path, crs=crs)
        points = np.concatenate([points, more])
    if s.altimetry_path:
        if s.altimetry_path.suffix.lower() == ".csv":
            more = checkpoints_io.read_checkpoints(s.altimetry_path).xyz
        else:
            more_lines, more = vectors.read_terrain_vectors(s.altimetry_path, crs=crs)
            lines += more_lines
        points = np.concatenate([points, more])
    if not lines and not len(points):
        return None
    s.notes.append(f"DTM honours {len(lines)} breaklines and {len(points)} spot heights")
    return lines, points


def _classified_cloud(s: RunState) -> PointCloud:
    """The input cloud with recon3d's classes: ground 2, vegetation 5, building 6, other 1,
    noise 7 (stereo points guessed over hidden ground), in a canonical order (by x, y,
    z, then GPS time and intensity), so that one survey gives the same file whether it
    came whole or in tiles, in any order."""
    cloud = s.cloud.with_attribute("classification", s.point_classes)
    a = cloud.attributes
    keys = [a[k] for k in ("intensity", "gps_time") if k in a] + [cloud.xyz[:, 2], cloud.xyz[:, 1], cloud.xyz[:, 0]]
    return cloud[np.lexsort(keys)]


def _write_footprints(s: RunState, *paths: Path) -> None:
    """The footprints with their building's status and heights, to each of ``paths``
    (GeoJSON, and a GeoPackage whose CRS GIS software reads whatever it is)."""
    u = s.units
    props = []
    for b in s.city:
        lods = sorted(b.solids, key=float)
        p = {"id": b.id, "status": b.status, "reason": b.reason or "", "lod": lods[-1] if lods else "",
             "roof_type": b.attributes.get("roof_type", "") if b.solids else ""}
        p.update(ground_z=_num(b.ground_z), roof_z=_num(b.roof_z), height_m=_num(b.height * u.vertical))
        p.update({k: v for k, v in b.attributes.items() if isinstance(v, str | int | float) and k not in p})
        props.append(p)
    for path in paths:
        vectors.write_features(path, [b.footprint for b in s.city], props, s.city.crs,
                               date=s.city.metadata.get("referenceDate"))


def _num(v: float) -> float | None:
    return round(float(v), 3) if np.isfinite(v) else None


def _run_record(s: RunState) -> dict:
    import laspy
    import rasterio
    import scipy
    import shapely
    import trimesh

    return {
        "recon3d": __version__,
        "inputs": {
            "input": str(s.input_path),
            "kind": "satellite pair" if s.satellite_paths else "stereo scene" if s.scene is not None
            else f"point cloud in {len(s.tile_paths)} tiles" if s.tile_paths else "point cloud",
            "tiles": [str(p) for p in s.tile_paths] if s.tile_paths else None,
            "second_image": str(s.satellite_paths[1]) if s.satellite_paths else None,
            "points": len(s.cloud),
            "crs": crs_name(s.cloud.crs),
            "crs_identification": s.crs_identification.record() if s.crs_identification else None,
            "units": {"horizontal": s.units.name, "metres_per_unit": s.units.horizontal,
                      "vertical_metres_per_unit": s.units.vertical, "vertical_from": s.units.vertical_source},
            "provider_classes": s.reference_classes is not None,
            "footprints": str(s.footprints_path) if s.footprints_path else None,
            "checkpoints": str(s.checkpoints_path) if s.checkpoints_path else None,
            "breaklines": str(s.breaklines_path) if s.breaklines_path else None,
            "altimetry": str(s.altimetry_path) if s.altimetry_path else None,
            "dem": str(s.dem_path) if s.dem_path else None,
            "old_buildings": str(s.old_buildings_path) if s.old_buildings_path else None,
            "gcps": str(s.gcps_path) if s.gcps_path else None,
        },
        "config": s.config.to_dict(),
        "chosen": s.auto,
        "local_frame_origin": list(s.city.frame.origin),
        "notes": s.notes,
        "warnings": s.warnings,
        "versions": {m.__name__: getattr(m, "__version__", "?") for m in (np, scipy, laspy, rasterio, shapely, trimesh)},
        "timings_s": s.timings,
    }


def _write_json(path: Path, data: dict) -> None:
    from recon3d.io import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, ensure_ascii=False, default=_json_default), encoding="utf-8")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")



