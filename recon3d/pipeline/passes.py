"""The per-point work of a run, one tile at a time.

Each pass is a plain function of one tile: it reads the tile's points (its core, or
its core and buffer) from the run's point store (the model DSM's pass reads none: it
ray-casts the solids over the tile's cells), computes what the stages need from
them, and returns it as arrays: rasters on the tile's core cells (the pipeline puts
them in place on the whole grid, where no other tile writes) and per-point values of
the core points (kept in the tile's folder for the later passes). Rasters the pass
reads come as windows of the whole grid (:class:`~recon3d.core.raster.Raster` with an
``origin``), so a point's cell and every value sampled at it are those of the whole
grid. The algorithms are the stage packages'; this module only cuts and joins.
"""

from __future__ import annotations

from dataclasses import astuple, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from recon3d.buildings import classes, vegetation
from recon3d.buildings.detect import fine_surface
from recon3d.config import PipelineConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud, column_bounds
from recon3d.core.raster import Raster
from recon3d.pipeline.points import CloudSummary, TilePoints, cell_rowcol, lexsort_ties
from recon3d.pipeline.tiling import BLOCK, Tile, morton
from recon3d.quality import buildings as building_quality
from recon3d.quality import evaluate
from recon3d.terrain import dsm as dsm_stage
from recon3d.terrain import dtm as dtm_stage
from recon3d.terrain import ground as ground_stage

__all__ = ["Spec", "building_points", "finish", "gather_building_points", "ground", "load", "surface", "vegetation_decide",
           "vegetation_features"]


@dataclass(frozen=True)
class Spec:
    """What every tile of a run shares (sent to each worker with its tile).

    Attributes
    ----------
    store : LasStore or MemoryStore
    transform : Affine
        The DSM grid's.
    shape : (rows, cols)
        The DSM grid's.
    folder : Path
        Where each tile keeps its per-point results (a folder per tile).
    config : PipelineConfig
    units : Units
    summary : CloudSummary
    stereo : {None, "frame", "satellite"}
    """

    store: Any
    transform: Affine
    shape: tuple[int, int]
    folder: Path
    config: PipelineConfig
    units: Units
    summary: CloudSummary
    stereo: str | None = None

    def core(self, tile: Tile) -> TilePoints:
        return self.store.read(tile.rows, tile.cols, self.transform)

    def window(self, tile: Tile, buffer: int) -> tuple[TilePoints, np.ndarray]:
        """The points of the tile and its buffer, and which of them are the core's."""
        rows, cols = tile.window(buffer, self.shape)
        pts = self.store.read(rows, cols, self.transform)
        return pts, pts.inside(tile.rows, tile.cols)

    def grid(self, tile: Tile) -> Raster:
        """An empty raster on the tile's core cells (a window of the DSM grid)."""
        shape = (tile.rows.stop - tile.rows.start, tile.cols.stop - tile.cols.start)
        return Raster(np.zeros(shape, np.float32), self.transform, self.store.summary.crs, {},
                      (tile.rows.start, tile.cols.start))

    def bounds(self, rows: slice, cols: slice) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the cells ``[rows, cols]`` of the DSM grid (a
        tile's core or window)."""
        t = self.transform
        return t.c + cols.start * t.a, t.f + rows.stop * t.e, t.c + cols.stop * t.a, t.f + rows.start * t.e


def load(spec: Spec, tile: Tile, name: str, *keys: str) -> dict[str, np.ndarray]:
    """The saved result of pass ``name`` for ``tile``: ``keys`` of it, or all of it."""
    with np.load(spec.folder / tile.name / f"{name}.npz") as data:
        return {k: data[k] for k in keys or data.files}


def cover(bounds: tuple, transform: Affine, shape: tuple[int, int], margin: int = 1) -> tuple[slice, slice]:
    """The cells of another grid (``transform``, ``shape``) under ``bounds`` (west, south,
    east, north), ``margin`` cells wider, clipped to that grid."""
    west, south, east, north = bounds
    c0 = int(np.floor((west - transform.c) / transform.a)) - margin
    c1 = int(np.floor((east - transform.c) / transform.a)) + 1 + margin
    r0 = int(np.floor((north - transform.f) / transform.e)) - margin
    r1 = int(np.floor((south - transform.f) / transform.e)) + 1 + margin
    return slice(max(r0, 0), min(r1, shape[0])), slice(max(c0, 0), min(c1, shape[1]))


def _highest(spec: Spec, cloud: PointCloud, grid: Raster, per_source: str | tuple[str, ...] | None = None):
    """(rows, cols) float64 DSM cells of ``cloud`` on ``grid`` before hole filling: the
    highest surface point (not noise) per cell, or for stereo the highest (frame) or
    median (satellite) observed point per pair and the median over the pairs
    (``per_source`` chooses another, or several: see :func:`~recon3d.terrain.dsm.grid_stereo`)."""
    keep, a = dsm_stage.surface_points(cloud), cloud.attributes
    if spec.stereo and "observed" in a:
        source = a.get("point_source_id")
        return dsm_stage.grid_stereo(
            cloud.xyz[keep], grid.transform, grid.shape, observed=(a["observed"] > 0)[keep],
            source=None if source is None else source[keep],
            per_source=per_source or ("median" if spec.stereo == "satellite" else "max"), origin=grid.origin,
        )
    return dsm_stage.grid_points(cloud.xyz, grid.transform, grid.shape, reducer="max", origin=grid.origin, keep=keep)


# --------------------------------------------------------------------------- passes


def surface(spec: Spec, tile: Tile, ground_transform: Affine, ground_shape: tuple[int, int]) -> dict:
    """The tile's cells of the DSM before hole filling (frame stereo: also from the upper
    median of each pair's points), its point counts and the lowest points of the ground
    filter's minimum surface (on its own grid: ``zmin`` over the window ``zmin_origin`` of
    it that the core covers, to be merged by minimum)."""
    pts = spec.core(tile)
    cloud, a = pts.cloud, pts.cloud.attributes
    grid = spec.grid(tile)
    T, shape, origin = grid.transform, grid.shape, grid.origin
    keep = dsm_stage.surface_points(cloud)
    out: dict[str, Any] = {}
    # frame stereo: the upper median for the cells outside the buildings (run._median_outside_buildings)
    if spec.stereo == "frame" and "observed" in a:
        out["dsm"], out["dsm_upper_median"] = _highest(spec, cloud, grid, ("max", "upper_median"))
    else:
        out["dsm"] = _highest(spec, cloud, grid)
    if spec.stereo and "observed" in a:
        out["observed"] = dsm_stage.grid_points(cloud.xyz, T, shape, reducer="count", origin=origin,
                                                keep=a["observed"] > 0)
        if "consistent" in a:
            # 1: the images agree with the guess; 2: filled beyond an occlusion's width
            for key, held in (("consistent", a["consistent"] > 0), ("foreground", a["consistent"] == 2)):
                out[key] = dsm_stage.grid_points(cloud.xyz, T, shape, reducer="count", origin=origin, keep=held)
    out["count"] = dsm_stage.grid_points(cloud.xyz, T, shape, reducer="count", origin=origin, keep=keep)
    out["points"] = dsm_stage.grid_points(cloud.xyz, T, shape, reducer="count", origin=origin)
    first = np.asarray(a["return_number"]) <= 1 if "return_number" in a else np.ones(len(cloud), bool)
    out["first_returns"] = np.int64(first.sum())
    rows, cols = cover(grid.bounds, ground_transform, ground_shape)
    out["zmin_origin"] = np.array([rows.start, cols.start])
    out["zmin"] = ground_stage.lowest_points(cloud, ground_transform, (rows.stop - rows.start, cols.stop - cols.start),
                                             quality_cut=spec.summary.quality_cut, origin=(rows.start, cols.start))
    seen = np.flatnonzero(first & keep)
    xy = cloud.xyz[seen, :2]
    out["surface_lo"], out["surface_hi"] = column_bounds(xy) if len(xy) else (np.full(2, np.inf), np.full(2, -np.inf))
    return out


def ground(spec: Spec, tile: Tile, terrain: Raster | None, noise: float, method: str) -> dict:
    """The tile's ground points (``terrain`` a window of the provisional terrain, None for
    the provider's classes), and the mean height and count of those shaping the DTM per cell."""
    pts = spec.core(tile)
    cloud, a = pts.cloud, pts.cloud.attributes
    if method == "provider":
        is_ground = cloud.classification == ASPRS.GROUND
        for_dtm = is_ground
    else:
        is_ground, for_dtm, _ = ground_stage.label_ground(cloud.xyz, terrain, spec.config.ground, spec.units,
                                                          noise=noise)
    shaping = for_dtm
    if spec.stereo and "observed" in a:
        shaping = shaping & (a["observed"] > 0)  # a filled-in disparity is no ground
    grid = spec.grid(tile)
    mean, count = dtm_stage.ground_cells(cloud.xyz, grid.transform, grid.shape, origin=grid.origin, keep=shaping)
    out = {"is_ground": is_ground, "for_dtm": for_dtm, "mean": mean, "count": count}
    if spec.summary.provider_classes:
        out["filter_counts"] = evaluate.filter_counts(is_ground, cloud.classification)
    return out


def vegetation_features(spec: Spec, tile: Tile, dtm: Raster, survey: vegetation.Survey, noise: float,
                        radius: float, buffer: int) -> dict:
    """Covariance features of the vegetation candidates of the tile and its buffer, and the
    counts of multi-return echoes among the core's (summed into the survey's rules)."""
    pts, core = spec.window(tile, buffer)
    cfg = spec.config.buildings
    cand = vegetation.vegetation_candidates(pts.cloud, dtm, cfg, spec.units, survey, radius=radius, order=pts.order)
    counts = vegetation.return_counts(cand, cfg, spec.units, noise, which=core[cand.index])
    out = {"index": cand.index, "roughness": cand.roughness, "scattering": cand.scattering,
           "neighbours": cand.neighbours.astype(np.int32), "counts": np.array(astuple(counts), np.int64)}
    if cand.multi is not None:
        out["multi"] = cand.multi
    if cand.colour is not None:
        out["colour"] = cand.colour
    return out


def vegetation_decide(spec: Spec, tile: Tile, survey: vegetation.Survey, noise: float, buffer: int,
                      plane_tolerance: float) -> dict:
    """Which core points are vegetation, their roughness, and the cells' vegetation and
    planar shares and highest first returns (the building detection's evidence)."""
    pts, core = spec.window(tile, buffer)
    f = load(spec, tile, "vegetation_features")  # every key: the candidates are the whole result
    cand = vegetation.Candidates(f["index"], f["roughness"], f["scattering"], f["neighbours"].astype(np.int64),
                                 f.get("multi"), f.get("colour"))
    veg = np.zeros(len(pts), bool)
    veg[cand.index] = vegetation.decide_vegetation(cand, spec.config.buildings, spec.units, survey, noise=noise)
    rough = np.full(len(pts), np.nan)
    rough[cand.index] = cand.roughness
    own = pts.subset(core)
    veg, rough = veg[core], rough[core]
    grid = spec.grid(tile)
    fine = fine_surface(own.cloud, grid, veg, order=own.order, pick="highest" if spec.stereo else "nearest")
    return {
        "vegetation": veg, "roughness": rough,
        "share": vegetation.vegetation_cells(own.cloud, grid, veg, share=True),
        "planar": vegetation.planar_cells(own.cloud, grid, rough, plane_tolerance),
        "fine_z": fine.z, "fine_vegetation": fine.vegetation,
    }


def building_points(spec: Spec, tile: Tile, boxes: np.ndarray, which: np.ndarray) -> dict:
    """The core points that may lie on roofs (neither ground nor vegetation) inside each
    building's bounding box: ``b<index>`` (k, 3) xyz and ``o<index>`` (k,) survey order,
    and ``counts`` (m,) how many each building has here.

    Parameters
    ----------
    boxes : (m, 4) float
        (xmin, ymin, xmax, ymax) of the buildings touching the tile.
    which : (m,) int
        Their indices among all buildings.
    """
    pts = spec.core(tile)
    roof = ~load(spec, tile, "ground", "is_ground")["is_ground"]
    roof &= ~load(spec, tile, "vegetation_decide", "vegetation")["vegetation"]
    xyz, order = pts.cloud.xyz[roof], pts.order[roof]
    out = {"counts": np.zeros(len(which), np.int64)}
    for k, ((x0, y0, x1, y1), i) in enumerate(zip(boxes, which, strict=True)):
        inside = (xyz[:, 0] >= x0) & (xyz[:, 0] <= x1) & (xyz[:, 1] >= y0) & (xyz[:, 1] <= y1)
        if inside.any():
            out[f"b{i}"], out[f"o{i}"] = xyz[inside], order[inside]
            out["counts"][k] = np.count_nonzero(inside)
    return out


def gather_building_points(paths: list[Path], index: int) -> np.ndarray:
    """(k, 3) the points of building ``index`` that :func:`building_points` saved in the
    tile results ``paths``, sorted by x (then survey order): the same whatever the tiling."""
    xyz, order = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
    for path in paths:
        with np.load(path) as data:
            xyz.append(data[f"b{index}"])
            order.append(data[f"o{index}"])
    xyz, order = np.concatenate(xyz), np.concatenate(order)
    return xyz[np.lexsort((order, xyz[:, 0]))]


def model_dsm(spec: Spec, tile: Tile, dtm: Raster, model: Any, top: float) -> dict:
    """The tile's core cells of the model DSM and of the roofs' cover
    (:func:`recon3d.quality.rasterize.render`).

    Parameters
    ----------
    dtm : Raster
        The core window of the DTM.
    model : CityModel
        The buildings with a solid whose footprints reach into the tile.
    top : float
        Where the rays start over the whole city (:func:`recon3d.quality.rasterize.ray_top`).
    """
    from recon3d.quality.rasterize import render

    model_dsm, cover = render(model, dtm, top=top)
    return {"model": model_dsm.data, "cover": cover}


@dataclass(frozen=True)
class Finish:
    """The rasters and the model the last pass reads around a tile.

    Attributes
    ----------
    labels, depth : (rows, cols) array
        Windows (one cell wider than the core, the cells of ``dtm``) of the footprint
        labels and the distance inside the footprints.
    dtm, dsm : Raster
        The same windows of the DTM and the DSM.
    with_solid : (m + 1,) bool
        Per label, whether its building has a solid.
    outlines : ((k,) int, list of k Polygon) or None
        Label and footprint of the buildings with a solid near the tile: the points
        of cells an outline crosses are judged against the polygons.
    roofs, model : CityModel or None
        The buildings touching the tile: with an LoD2.2 solid; with any solid.
    roofs_top, model_top : float
        Where the rays start over the whole city (:func:`recon3d.quality.rasterize.ray_top`).
    tolerance, plane_tolerance : float
        Of :func:`recon3d.buildings.classes.point_classes`.
    hidden_ground : bool
        Stereo: DSM cells were lowered to the DTM; points above them are noise.
    reference_grid : ReferenceGrid or None
        The provider-class evaluation grid (with provider classes).
    buffer : int
        Cells of points read around the core for the evaluation grid.
    crowns : (rows, cols) bool or None
        The same window of the cells of detected blobs found to be tree crowns: their
        points above ``vegetation_min_height`` are vegetation.
    sunk : (rows, cols) bool or None
        The same window of the DTM cells interpolated again under the ground tie points
        (frame stereo): their ground points more than ``SUNK_MARGIN`` below the DTM are
        low noise (7).
    """

    labels: np.ndarray
    depth: np.ndarray
    dtm: Raster
    dsm: Raster
    with_solid: np.ndarray
    roofs: Any
    model: Any
    roofs_top: float
    model_top: float
    tolerance: float
    plane_tolerance: float
    hidden_ground: bool
    reference_grid: building_quality.ReferenceGrid | None
    buffer: int
    crowns: np.ndarray | None = None
    sunk: np.ndarray | None = None
    outlines: tuple[np.ndarray, list] | None = None


def finish(spec: Spec, tile: Tile, f: Finish) -> dict:
    """The classes of the core points (cloud.laz's records of the tile, in file order),
    the model scanned at them, and the counts and errors of the accuracy report."""
    from recon3d.quality.rasterize import surface_at

    u, cfg = spec.units, spec.config.buildings
    reference = None
    if f.reference_grid is None:
        own = spec.core(tile)
    else:  # the buffered points judge the reference cells, then go before the core's work begins
        pts, core = spec.window(tile, f.buffer)
        reference = _reference_cells(spec, tile, pts, f.reference_grid)
        own = pts.subset(core)
        del pts, core
    cloud, xyz = own.cloud, own.cloud.xyz
    is_ground = load(spec, tile, "ground", "is_ground")["is_ground"]
    decided = load(spec, tile, "vegetation_decide", "vegetation", "roughness")
    veg, rough = decided["vegetation"], decided["roughness"]
    row, col = f.dtm.rowcol(xyz[:, 0], xyz[:, 1])
    if f.crowns is not None:
        height = xyz[:, 2] - f.dtm.sample(xyz[:, 0], xyz[:, 1], bilinear=False)
        veg = veg | (f.crowns[row, col] & ~is_ground & (np.nan_to_num(height) >= u.height(cfg.vegetation_min_height)))
    roof_surface = None
    if f.roofs is not None:
        inside = f.labels[row, col] > 0
        roof_surface = np.full(len(xyz), np.nan)
        if inside.any():
            nowhere = f.dtm.like(np.full(f.dtm.shape, np.nan, np.float32))
            roof_surface[inside] = surface_at(f.roofs, xyz[inside, 0], xyz[inside, 1], nowhere, lod="2.2",
                                              top=f.roofs_top)
    point_classes = classes.point_classes(
        cloud, is_ground, f.labels, f.dtm, f.dtm, cfg, u, vegetation=veg, with_solid=f.with_solid,
        roof_surface=roof_surface, roughness=rough, tolerance=f.tolerance, plane_tolerance=f.plane_tolerance,
        depth=f.depth, outlines=f.outlines,
    )
    if f.sunk is not None:  # the mismatches a sunk DTM was interpolated over again: low points, not ground
        from recon3d.stereo.check import SUNK_MARGIN

        low = f.sunk[row, col] & (point_classes == ASPRS.GROUND)
        low &= xyz[:, 2] < f.dtm.data[row, col] - u.height(SUNK_MARGIN)
        point_classes[low] = ASPRS.NOISE
    if f.hidden_ground:  # the guesses over hidden ground stay in the cloud, above the DSM that replaced them
        above = xyz[:, 2] > f.dsm.sample(xyz[:, 0], xyz[:, 1], bilinear=False) + u.height(0.5)
        point_classes[above] = ASPRS.NOISE
    out: dict[str, Any] = {"classes": point_classes}
    out["scan"] = _scan(spec, tile, own, f)
    if spec.summary.provider_classes:
        out.update(_provider_scores(spec, own, point_classes, f, reference))
    out.update(_records(own, point_classes))
    return out


def _scan(spec: Spec, tile: Tile, own: TilePoints, f: Finish) -> np.ndarray:
    """The tile's cells of the model scanned at the points: each point's height replaced by
    the model's surface above it (the terrain beside the buildings), gridded like the DSM."""
    from recon3d.quality.rasterize import surface_at

    xyz = own.cloud.xyz
    if f.model is None:
        z = f.dtm.sample(xyz[:, 0], xyz[:, 1], bilinear=True)
    else:
        z = surface_at(f.model, xyz[:, 0], xyz[:, 1], f.dtm, top=f.model_top)
    scanned = PointCloud(np.column_stack([xyz[:, :2], z]), own.cloud.attributes, own.cloud.crs)[np.isfinite(z)]
    return _highest(spec, scanned, spec.grid(tile))


def _provider_scores(spec: Spec, own: TilePoints, point_classes: np.ndarray, f: Finish, reference: tuple) -> dict:
    """The counts and errors of the report's comparisons with the provider's classes;
    ``reference``: the tile's :func:`_reference_cells`."""
    u = spec.units
    cloud = own.cloud
    ref = cloud.classification
    xyz = cloud.xyz
    height = xyz[:, 2] - f.dtm.sample(xyz[:, 0], xyz[:, 1])
    truth = building_quality.vegetation_truth_proxy(cloud, ref, height, min_height=u.height(2.5),
                                                    colour=spec.summary.colour)
    ground = ref == ASPRS.GROUND
    out = {
        "vegetation_counts": np.array(building_quality.vegetation_counts(truth, point_classes), np.int64),
        "coverage_counts": evaluate.coverage_counts(cloud, ref, f.labels, f.dtm),
        "ground_errors": (-height[ground]).astype(np.float32),  # the DTM minus the point: the same bits
        "ground_count": np.int64(np.count_nonzero(ground)),
    }
    window, valid, building = reference
    out.update(reference_window=window, reference_valid=valid, reference_building=building)
    return out


#: Farthest a reference grid cell's point may lie (m), as in evaluate_against_classes.
REFERENCE_DISTANCE = 1.0


def _reference_cells(spec: Spec, tile: Tile, pts: TilePoints, grid: building_quality.ReferenceGrid):
    """The block of the provider-class evaluation grid whose cell centres lie in the tile's
    core: its (row start, row stop, col start, col stop), and per cell (block-shaped bool)
    whether a surface point lies near enough and whether it is of the building class."""
    rs, cs = cover(spec.bounds(tile.rows, tile.cols), grid.transform, grid.shape)
    none = np.zeros(4, np.int64), np.zeros((0, 0), bool), np.zeros((0, 0), bool)
    if rs.stop <= rs.start or cs.stop <= cs.start:
        return none
    gx, gy = grid.centres(rs, cs)
    row, _ = cell_rowcol(np.column_stack([gx[:, 0], gy[:, 0]]), spec.transform)
    _, col = cell_rowcol(np.column_stack([gx[0], gy[0]]), spec.transform)
    # a cell's row on the DSM grid follows from its centre's y alone, its column from x
    rows = np.flatnonzero((row >= tile.rows.start) & (row < tile.rows.stop))
    cols = np.flatnonzero((col >= tile.cols.start) & (col < tile.cols.stop))
    if not len(rows) or not len(cols):
        return none
    block = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    centres = np.column_stack([gx[block].ravel(), gy[block].ravel()])
    seen = building_quality.surface_points(pts.cloud)
    valid, nearest = building_quality.nearest_point(
        pts.cloud.xyz[seen, :2], centres, spec.units.length(REFERENCE_DISTANCE), order=pts.order[seen])
    building = np.zeros(len(centres), bool)
    building[valid] = pts.cloud.classification[seen][nearest[valid]] == ASPRS.BUILDING
    shape = (len(rows), len(cols))
    window = np.array([rs.start + rows[0], rs.start + rows[-1] + 1, cs.start + cols[0], cs.start + cols[-1] + 1])
    return window, valid.reshape(shape), building.reshape(shape)


def _records(own: TilePoints, point_classes: np.ndarray) -> dict:
    """The tile's points, with recon3d's classes, as cloud.laz holds them: in the order of
    their blocks' Morton codes, then x, y, z, GPS time and intensity (the same for every tiling)."""
    cloud, row, col = own.cloud.with_attribute("classification", point_classes), own.row, own.col
    a = cloud.attributes
    keys = [a[k] for k in ("intensity", "gps_time") if k in a]
    keys += [cloud.xyz[:, 2], cloud.xyz[:, 1], cloud.xyz[:, 0], morton(row // BLOCK, col // BLOCK)]
    order = lexsort_ties(keys, 3)
    out = {"xyz": cloud.xyz[order]}
    out.update({f"a_{k}": np.asarray(v)[order] for k, v in a.items()})
    return out


def with_counts(survey: vegetation.Survey, counts: np.ndarray) -> vegetation.Survey:
    """The survey's vegetation rules with the multi-return counts summed over the tiles."""
    return replace(survey, counts=vegetation.ReturnCounts(*(int(v) for v in counts)))
