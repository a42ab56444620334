"""Reading a run's inputs: the points (or the stereo images that give them) and the
vectors, rasters and check points beside them, all checked before anything is computed."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyproj

from recon3d.core.geo import CRSIdentification, Units, crs_name, crs_units, identify_crs
from recon3d.core.pointcloud import PointCloud
from recon3d.core.raster import Raster
from recon3d.errors import InputError
from recon3d.io import checkpoints as checkpoints_io
from recon3d.io import vectors
from recon3d.io.las import las_date
from recon3d.pipeline.points import GROSS_HEIGHT_ERROR, CloudSummary, LasStore, MemoryStore

log = logging.getLogger(__name__)

__all__ = ["MAX_ABS_HEIGHT", "MIN_POINTS", "Inputs", "Source"]

#: Fewest points a run works with: fewer make no DSM worth the name, let alone buildings.
MIN_POINTS = 100

#: Largest magnitude of heights (m): beyond it float32 rasters no longer hold
#: centimetres (their step at 131 km is 1.6 cm), and a wrong vertical offset or unit is
#: far more likely than real data.
MAX_ABS_HEIGHT = 1e5

#: Least share (percent) of the pixels both satellite images see that must be matched
#: (not filled in) without a warning.
MIN_SATELLITE_MATCHED = 80.0

#: Metres the tallest object may stand above a ``--dem`` of a satellite pair when
#: ``stereo.max_object_height`` is not set (the DEM's own error is ``stereo.dem_tolerance``).
SATELLITE_OBJECT_HEIGHT = 50.0


@dataclass
class Inputs:
    """The files a run was given (None: not given)."""

    input_path: Path
    tile_paths: list[Path] | None = None  # LAS/LAZ tiles of one survey
    satellite_paths: tuple[Path, Path] | None = None
    crs: pyproj.CRS | None = None
    footprints: Path | None = None
    checkpoints: Path | None = None
    breaklines: Path | None = None
    altimetry: Path | None = None
    dem: Path | None = None
    truth_dsm: Path | None = None
    old_buildings: Path | None = None
    gcps: Path | None = None

    @property
    def kind(self) -> str:
        """"points", "frame" or "satellite"."""
        from recon3d.io.colmap import is_scene_folder

        if self.satellite_paths is not None:
            return "satellite"
        return "frame" if is_scene_folder(self.input_path) else "points"

    def given(self) -> list[Path]:
        """Every path the run reads (the output folder must not touch them)."""
        paths = [self.input_path, *(self.satellite_paths or ()), *(self.tile_paths or ()), self.footprints,
                 self.checkpoints, self.breaklines, self.altimetry, self.dem, self.truth_dsm, self.old_buildings,
                 self.gcps]
        return [Path(p) for p in paths if p]


@dataclass
class Source:
    """What was read: the points (a store a tile at a time) and everything beside them.

    Attributes
    ----------
    store : LasStore or MemoryStore or None
        None until a stereo input is matched.
    summary : CloudSummary or None
    units : Units
    scene : StereoScene, or the two RPC cameras of a satellite pair, or None
    """

    store: Any = None
    summary: CloudSummary | None = None
    units: Units | None = None
    crs_identification: CRSIdentification | None = None
    reference_date: str | None = None
    scene: Any = None
    views: list | None = None
    dem: Raster | None = None
    gcps: Any = None
    footprints: list | None = None
    checkpoints: checkpoints_io.CheckPoints | None = None
    old_buildings: list | None = None
    constraints: tuple[list[np.ndarray], np.ndarray] | None = None
    stereo: dict = field(default_factory=dict)  # run.json's record of the matching

    @property
    def crs(self) -> pyproj.CRS:
        return self.summary.crs


def read_points(inputs: Inputs, folder: Path, *, auto: dict, progress=None, executor=None) -> Source:
    """The points of a LAS/LAZ or PLY input (bucketed in ``folder`` for LAS/LAZ), checked."""
    suffix = inputs.input_path.suffix.lower()
    source = Source()
    if inputs.tile_paths or suffix in (".las", ".laz"):
        paths = inputs.tile_paths or [inputs.input_path]
        report = (lambda done, total: progress(f"{done / 1e6:.1f} of {total / 1e6:.1f} M points")) if progress else None
        source.store = LasStore.open(paths, folder, crs=inputs.crs, progress=report, executor=executor)
        dates = [d for d in map(las_date, paths) if d]
        if dates:
            source.reference_date = max(dates)
            auto["reference_date"] = {"value": source.reference_date,
                                      "reason": f"latest LAS header creation date of the {len(paths)} tiles"
                                      if len(paths) > 1 else "LAS header creation date"}
    elif suffix == ".ply":
        from recon3d.io.ply import read_ply

        source.store = MemoryStore(read_ply(inputs.input_path, crs=inputs.crs))
    elif not inputs.input_path.exists():
        raise InputError(f"{inputs.input_path}: input not found")
    else:
        raise InputError(
            f"{inputs.input_path}: unsupported input (expected .las, .laz, .ply or a folder with images/ and sparse/)"
        )
    return source


def check_points(source: Source, inputs: Inputs, warn) -> None:
    """The summary's CRS identified, the units known, the cloud physically sane."""
    s = source.summary = source.store.summary
    source.crs_identification = identify_crs(s.crs)
    s.crs = source.crs_identification.crs
    source.store.crs = s.crs
    for message in source.crs_identification.warnings():
        warn(message)
    u = source.units = crs_units(s.crs, source=str(inputs.input_path))
    if s.count < MIN_POINTS:
        raise InputError(f"{inputs.input_path}: {s.count} points: too few for a DSM and buildings (at least {MIN_POINTS})")
    if s.gross:
        warn(f"{s.gross} points lie more than {GROSS_HEIGHT_ERROR:g} m from the median height "
             f"{s.median_z:.1f}: gross errors, left out")
    if s.repeats:
        warn(f"{s.repeats} points are in two overlapping tiles (same x, y, z and GPS time); each is kept once")
    if abs(s.median_z) * u.vertical > MAX_ABS_HEIGHT:
        raise InputError(
            f"{inputs.input_path}: heights around {s.median_z:.6g} {u.name}: rasters cannot hold them to the "
            "centimetre; is the vertical offset or unit wrong?"
        )
    extent = np.ptp(s.bounds[:, :2], axis=0)
    if extent.min() < u.length(2.0):
        raise InputError(
            f"{inputs.input_path}: the points span {extent[0]:.3g} x {extent[1]:.3g} {u.name}: no area to grid"
        )


def read_scene(inputs: Inputs, source: Source, notes: list) -> None:
    """A stereo input: the frame scene or the satellite cameras, and what bounds their matching."""
    from recon3d.io.colmap import read_scene as read_colmap

    if inputs.satellite_paths is not None:
        from recon3d.io.rpc import read_rpc_camera

        source.scene = [read_rpc_camera(p) for p in inputs.satellite_paths]
        if inputs.gcps:
            source.gcps = checkpoints_io.read_checkpoints(inputs.gcps)
        if inputs.dem:
            source.dem = _read_satellite_dem(inputs.dem, source.scene[0])
        return
    source.scene = read_colmap(inputs.input_path, crs=inputs.crs)
    source.units = crs_units(source.scene.crs, source=str(inputs.input_path))
    world = source.scene.sparse + source.scene.offset
    read_vectors(inputs, source, source.scene.crs, (world.min(axis=0), world.max(axis=0)), notes)


def read_vectors(inputs: Inputs, source: Source, crs: pyproj.CRS, bounds, notes: list) -> None:
    """Footprints, check points, old buildings, terrain constraints and the DEM, in ``crs``;
    ``bounds`` (lowest, highest corner) is the extent the footprints must overlap."""
    if inputs.footprints:
        source.footprints, more = vectors.read_footprints(inputs.footprints, crs=crs)
        notes += more
        _check_overlap(inputs, source, bounds, crs)
    if inputs.checkpoints:
        source.checkpoints = checkpoints_io.read_checkpoints(inputs.checkpoints)
    if inputs.old_buildings:
        source.old_buildings, more = vectors.read_footprints(inputs.old_buildings, crs=crs)
        notes += more
    source.constraints = _read_constraints(inputs, crs, notes)
    if inputs.dem and source.dem is None:
        from recon3d.io.geotiff import read_dem

        source.dem = read_dem(inputs.dem, crs=crs, bounds=bounds)


def _check_overlap(inputs: Inputs, source: Source, bounds, crs: pyproj.CRS) -> None:
    import shapely

    lo, hi = bounds
    box = shapely.box(lo[0], lo[1], hi[0], hi[1])
    what = "the point cloud" if source.scene is None else "the scene's sparse points"
    if not any(f.polygon.intersects(box) for f in source.footprints):
        raise InputError(
            f"{inputs.footprints}: none of the {len(source.footprints)} footprints overlaps {what} "
            f"(extent {lo[0]:.1f},{lo[1]:.1f} - {hi[0]:.1f},{hi[1]:.1f} in {crs_name(crs)}); "
            "check the footprints' CRS"
        )


def _read_constraints(inputs: Inputs, crs: pyproj.CRS, notes: list) -> tuple[list[np.ndarray], np.ndarray] | None:
    """Breaklines and spot heights for the DTM, or None when neither was given."""
    lines, points = [], np.zeros((0, 3))
    if inputs.breaklines:
        lines, more = vectors.read_terrain_vectors(inputs.breaklines, crs=crs)
        points = np.concatenate([points, more])
    if inputs.altimetry:
        if inputs.altimetry.suffix.lower() == ".csv":
            more = checkpoints_io.read_checkpoints(inputs.altimetry).xyz
        else:
            more_lines, more = vectors.read_terrain_vectors(inputs.altimetry, crs=crs)
            lines += more_lines
        points = np.concatenate([points, more])
    if not lines and not len(points):
        return None
    notes.append(f"DTM honours {len(lines)} breaklines and {len(points)} spot heights")
    return lines, points


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


def match_frame(source: Source, config, *, warn, progress) -> PointCloud:
    """Dense matching of a frame scene (bounded by the vectors and the DEM when given)."""
    from recon3d.pipeline.stereo import dense_cloud, matching_constraints

    bounds = matching_constraints(source.scene, config.stereo, source.units, dem=source.dem,
                                  footprints=source.footprints, constraints=source.constraints)
    cloud, source.stereo = dense_cloud(source.scene, config.stereo, bounds=bounds, warn=warn, progress=progress,
                                       units=source.units)
    return cloud


def match_satellite(inputs: Inputs, source: Source, config, *, warn, progress) -> PointCloud:
    """RPC pair to a cloud in the scene's UTM zone (or the CRS given with --crs)."""
    import rasterio

    from recon3d.stereo.satellite import dense_cloud_rpc

    a, b = source.scene
    images = []
    for cam in (a, b):
        with rasterio.open(cam.image_path) as src:
            images.append(src.read(1, masked=True).astype(np.float32).filled(np.nan))
    cfg = config.stereo
    cloud, report = dense_cloud_rpc(
        a, b, *images, tile_size=cfg.tile_size, engine=cfg.engine, dem=source.dem,
        dem_tolerance=cfg.dem_tolerance + (cfg.max_object_height or SATELLITE_OBJECT_HEIGHT), progress=progress,
    )
    if report.get("self_check_warning"):
        warn(report["self_check_warning"])
    for f in report["tiles"]["failures"]:
        warn(f"satellite tile {f['tile']} (pixels {f['core']} of {a.image_path.name}) failed: {f['reason']}")
    if report["matched_percent"] < MIN_SATELLITE_MATCHED:
        warn(f"only {report['matched_percent']:.0f} % of the pixels both images see were matched "
             f"(expected >= {MIN_SATELLITE_MATCHED:.0f} %); the rest is filled in and left out of the DTM and buildings")
    report["crs"] = {"value": crs_name(cloud.crs), "reason": "UTM zone of the scene centre"}
    if inputs.crs is not None:
        t = pyproj.Transformer.from_crs(cloud.crs, inputs.crs, always_xy=True)
        x, y = t.transform(cloud.xyz[:, 0], cloud.xyz[:, 1])
        cloud = PointCloud(np.column_stack([x, y, cloud.xyz[:, 2]]), cloud.attributes, inputs.crs)
        report["crs"] = {"value": crs_name(inputs.crs), "reason": "--crs"}
    if source.gcps is not None:
        from recon3d.stereo.satellite import absolute_shift

        shift, report["absolute_bias"] = absolute_shift(cloud, source.gcps.xyz)
        cloud = PointCloud(cloud.xyz + shift, cloud.attributes, cloud.crs)
    source.stereo = report
    return cloud
