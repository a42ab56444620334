"""Time the Pleiades Giza pair (about 800 x 800 px) from RPC crops to a DSM, single tile vs tiled.

Usage::

    .venv/bin/python scripts/bench_giza.py [TILE_SIZE ...]

Without arguments it compares the default (one tile for this crop) with 400 and 300 px
tiles. For each it prints the time from the images to the DSM (issue target <= 30 s),
the residual vertical parallax pooled over the tiles and per tile, the point count,
the DSM density (share of the cells over the cloud's footprint that received points
before hole filling) and the Khufu pyramid's height above the plateau (about 139 m).

It then shows why tiles matter on larger scenes, from the RPCs alone (the images are
800 px crops, but the RPCs cover the full scenes): for square windows of the first
scene centred on the crop, the largest row difference the affine approximation leaves
on RPC correspondences (``affine_residual_px``), one affine map for the window vs one
per 800 px tile.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pyproj
import rasterio

from recon3d.core.geo import crs_units
from recon3d.core.raster import grid_for_bounds
from recon3d.io.rpc import read_rpc_camera
from recon3d.io.rpc import RPCCamera
from recon3d.quality.evaluate import landmark_height
from recon3d.stereo.satellite import (
    AUTO_TILE,
    _affine_maps,
    _apply,
    _epipolar_geometry,
    _sub_camera,
    dense_cloud_rpc,
    tile_grid,
)
from recon3d.terrain import dsm as dsm_stage

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "stereo" / "pleiades_gizeh"
KHUFU = (31.134225, 29.979175)  # lon, lat


def load():
    cams = [read_rpc_camera(DATA / f"img{i}.tif") for i in (1, 2)]
    images = []
    for cam in cams:
        with rasterio.open(cam.image_path) as src:
            images.append(src.read(1, masked=True).astype(np.float32).filled(np.nan))
    return cams, images


def khufu_height(dsm) -> tuple[float, float]:
    """Khufu above the plateau just outside its 230 m base (m): mean of the 5 highest
    cells within 60 m of the centre, and the highest cell."""
    e, n = pyproj.Transformer.from_crs(4326, dsm.crs, always_xy=True).transform(*KHUFU)
    khufu = landmark_height(dsm, e, n, search=60.0, ring=(118.0, 130.0))
    return khufu["top5"], khufu["apex"]


def run(tile_size: int | None) -> None:
    t0 = time.perf_counter()
    (a, b), images = load()
    cloud, report = dense_cloud_rpc(a, b, *images, tile_size=tile_size)
    t1 = time.perf_counter()
    spacing = dsm_stage.point_spacing(cloud.xyz[:, :2])
    res, _ = dsm_stage.choose_resolution(spacing, crs_units(cloud.crs))  # as the pipeline does
    lo, hi = cloud.bounds
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], res)
    raw = dsm_stage.grid_points(cloud.xyz, transform, shape, reducer="max")
    dsm = dsm_stage.make_dsm(cloud, res, max_hole_cells=int(200 / res**2), rim="low")
    t2 = time.perf_counter()
    tiles = report["tiles"]
    footprint = np.isfinite(dsm.data)
    density = 100.0 * float(np.isfinite(raw)[footprint].mean()) if footprint.any() else float("nan")
    label = "auto" if tile_size is None else f"{tile_size} px"
    print(f"\n== tile size {label}: {tiles['count']} tile(s) of <= {tiles['tile_size_px']} px, {tiles['failed']} failed")
    print(f"   time: images -> cloud {t1 - t0:.1f} s, cloud -> DSM {t2 - t1:.1f} s, total {t2 - t0:.1f} s (target <= 30 s)")
    vp = report["vertical_parallax_px"]
    print(f"   vertical parallax: median {vp['median']} px, p90 {vp['p90']} px over {vp['n']} matches")
    print(f"   points {report['points']}, spacing {spacing:.2f} m, matched {report['matched_percent']} %, "
          f"DSM {res} m cells: {density:.1f} % filled before hole filling")
    top5, apex = khufu_height(dsm)
    print(f"   Khufu above the plateau: top-5 mean {top5:.1f} m, highest cell {apex:.1f} m (expected ~139 m)")
    print(f"   affine model residual {report['affine_residual_px']} px (largest over the tiles)")
    for r in tiles["per_tile"]:
        p = r["vertical_parallax_px"]
        print(f"   tile {r['tile']:2d} core {r['core']}: parallax median {p['median']} p90 {p['p90']} (n {p['n']}), "
              f"disparities {r['disparity_range']}, bias {r['bias_px']} ({r['bias_from']}), {r['points']} points")


def affine_residual(a: RPCCamera, b: RPCCamera) -> float:
    """Largest row difference (px) of RPC correspondences after one affine map per image."""
    heights, p1, p2, hh, d1, _ = _epipolar_geometry(a, b)
    A1, A2 = _affine_maps(p1, p2, hh == heights[len(heights) // 2], d1)
    return float(np.abs(_apply(A1, p1)[:, 1] - _apply(A2, p2)[:, 1]).max())


def model_only(windows=(800, 2000, 5000, 10000)) -> None:
    (a, b), _ = load()
    full_a = RPCCamera(a.model, int(2 * a.model.samp_off + 1), int(2 * a.model.line_off + 1), name="scene1")
    full_b = RPCCamera(b.model, int(2 * b.model.samp_off + 1), int(2 * b.model.line_off + 1), name="scene2")
    cc, cr = a.col0 + a.width / 2, a.row0 + a.height / 2
    print(f"\n== affine model residual (RPCs only), {AUTO_TILE} px tiles")
    for n in windows:
        box = np.array([cc - n / 2, cr - n / 2, cc + n / 2, cr + n / 2]).round().astype(int)
        window = _sub_camera(full_a, box, f"window{n}")
        one = affine_residual(window, full_b)
        cores, _ = tile_grid(n, n, AUTO_TILE, 0)
        tiled = max(affine_residual(_sub_camera(window, core, "tile"), full_b) for core in cores)
        print(f"   {n:5d} px window: one affine map {one:.3f} px, {len(cores)} tiles {tiled:.3f} px (max)")


def main(argv: list[str]) -> None:
    sizes = [int(v) for v in argv] if argv else [None, 400, 300]
    for size in sizes:
        run(size)
    model_only()


if __name__ == "__main__":
    main(sys.argv[1:])
