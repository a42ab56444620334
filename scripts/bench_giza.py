"""Time the Pleiades Giza pair (about 800 x 800 px) from RPC crops to a DSM, single tile vs tiled.

Usage::

    .venv/bin/python scripts/bench_giza.py [TILE_SIZE ...] [--data DIR] [--quick]

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

``--quick`` matches a 300 px crop of the first image around Khufu (and the part of
the second that sees it) in one tile, and the RPC residuals of the 800 and 2000 px
windows only; the crop is too small for the plateau ring, so Khufu's height is not
checked there.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import _bench
import numpy as np
import pyproj
import rasterio

from recon3d.core.geo import crs_units
from recon3d.core.raster import grid_for_bounds
from recon3d.io.rpc import RPCCamera, read_rpc_camera
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

DATA = _bench.SHARED / "stereo" / "pleiades_gizeh"
KHUFU = (31.134225, 29.979175)  # lon, lat
QUICK_HALF = 150  # px: --quick crops 300 x 300 px of the first image around Khufu
QUICK_WINDOWS = (800, 2000)


def load(data: Path = DATA):
    cams = [read_rpc_camera(data / f"img{i}.tif") for i in (1, 2)]
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


def quick_crop(cams, images, half: int = QUICK_HALF, margin: int = 30):
    """``2 half`` px of the first image around Khufu and the box of the second seeing it (RPC height range)."""
    (a, b), (ia, ib) = cams, images
    r, c = (float(v) for v in a.project(*KHUFU, 200.0))
    r0, c0 = int(max(r - half, 0)), int(max(c - half, 0))
    box_a = (c0, r0, min(c0 + 2 * half, a.width), min(r0 + 2 * half, a.height))
    rows = np.array([box_a[1], box_a[1], box_a[3], box_a[3]] * 2, float)
    cols = np.array([box_a[0], box_a[2], box_a[0], box_a[2]] * 2, float)
    hs = np.repeat(a.model.height_range, 4)
    rb, cb = b.project(*a.localize(rows, cols, hs), hs)
    box_b = (max(int(cb.min()) - margin, 0), max(int(rb.min()) - margin, 0),
             min(int(cb.max()) + margin, b.width), min(int(rb.max()) + margin, b.height))
    crops = [im[y0:y1, x0:x1] for im, (x0, y0, x1, y1) in ((ia, box_a), (ib, box_b))]
    return (_sub_camera(a, box_a, "img1 crop"), _sub_camera(b, box_b, "img2 crop")), crops


def run(tile_size: int | None, data: Path = DATA, quick: bool = False) -> None:
    t0 = time.perf_counter()
    (a, b), images = quick_crop(*load(data)) if quick else load(data)
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
    if quick:
        print("   Khufu above the plateau: not checked on the --quick crop (the plateau ring lies outside it)")
    else:
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


def model_only(windows=(800, 2000, 5000, 10000), data: Path = DATA) -> None:
    (a, b), _ = load(data)
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sizes", nargs="*", type=int, metavar="TILE_SIZE", help="tile sizes (px) to compare")
    parser.add_argument("--data", type=Path, default=DATA, help="folder of img1.tif, img2.tif (default: %(default)s)")
    _bench.add_quick(parser)
    args = parser.parse_args(argv)
    for name in ("img1.tif", "img2.tif"):
        _bench.require(args.data / name, "Pleiades image")
    sizes = [None] if args.quick else (args.sizes or [None, 400, 300])
    for size in sizes:
        run(size, args.data, args.quick)
    model_only(QUICK_WINDOWS if args.quick else (800, 2000, 5000, 10000), args.data)


if __name__ == "__main__":
    _bench.guard(main)
