"""Satellite stereo on the Pleiades pair over Giza: RPC crops to a DSM in UTM 36N."""

import json
import shutil

import numpy as np
import pyproj
import pytest
import rasterio
from click.testing import CliRunner

from conftest import shared
from recon3d.cli import cli
from recon3d.io.geotiff import read_raster

IMG1, IMG2 = "stereo/pleiades_gizeh/img1.tif", "stereo/pleiades_gizeh/img2.tif"
KHUFU = (31.134225, 29.979175)  # lon, lat of the Great Pyramid's centre


@pytest.fixture(scope="module")
def giza(tmp_path_factory):
    from recon3d.pipeline.run import run

    out = tmp_path_factory.mktemp("giza") / "out"
    return run((shared(IMG1), shared(IMG2)), out)


def _pyramid(dsm):
    """Khufu's apex above the plateau (highest cell, mean of the 5 highest) and base width (m).

    The base is the median height of a ring just outside the 230 m base; the width is
    the run of cells more than 2 m above it along east-west lines, the median over the
    line through the apex and lines 10 and 20 m north and south of it (one line alone
    moves by several metres with the matching noise at the foot of the faces).
    """
    from recon3d.quality.evaluate import landmark_height

    e, n = pyproj.Transformer.from_crs(4326, dsm.crs, always_xy=True).transform(*KHUFU)
    khufu = landmark_height(dsm, e, n, search=60.0, ring=(118.0, 130.0))  # ring just outside the base
    iy, ix, base, z = khufu["row"], khufu["col"], khufu["base"], dsm.data
    widths = []
    for row in iy + np.rint(np.array([-20, -10, 0, 10, 20]) / dsm.resolution).astype(int):
        above = np.nan_to_num(z[row], nan=-1e9) > base + 2  # the base along an east-west line
        lo = hi = ix
        while lo > 0 and above[lo - 1]:
            lo -= 1
        while hi < len(above) - 1 and above[hi + 1]:
            hi += 1
        widths.append((hi - lo) * dsm.resolution)
    return khufu["apex"], khufu["top5"], float(np.median(widths))


def test_landmark_height_of_a_cone():
    """A 40 m cone of 30 m radius on ground at 100 m: apex and top-5 above the ring around it."""
    from affine import Affine

    from recon3d.core.raster import Raster
    from recon3d.quality.evaluate import landmark_height

    transform = Affine(1.0, 0.0, 1000.0, 0.0, -1.0, 2100.0)
    x, y = np.meshgrid(np.arange(100) + 1000.5, 2100 - np.arange(100) - 0.5)
    z = 100.0 + np.maximum(0.0, 40.0 * (1 - np.hypot(x - 1050.5, y - 2050.5) / 30.0))
    z[10, 10] = np.nan  # nodata is ignored
    out = landmark_height(Raster(z.astype(np.float32), transform), 1048.0, 2052.0, search=10.0, ring=(32.0, 40.0))
    assert out["apex"] == pytest.approx(40.0, abs=1e-3)
    assert 37.0 < out["top5"] < 40.0
    assert out["base"] == pytest.approx(100.0) and (out["row"], out["col"]) == (49, 50)


def test_dsm_in_utm_with_the_pyramid(giza):
    dsm = read_raster(giza.out_dir / "dsm.tif")
    assert dsm.crs.to_epsg() == 32636  # chosen from the scene centre
    apex, top5, width = _pyramid(dsm)
    # the summit's cells scatter by +-3 m (stepped masonry, matching noise): the single
    # highest cell gives 139.5 m, the mean of the five highest 139.2 m (issue: 139 +- 3)
    assert apex == pytest.approx(139.0, abs=3.5)
    assert top5 == pytest.approx(139.0, abs=3.0)
    # measured 225 m; 2 m above the plateau the 51.8 deg faces are 1.6 m inside the 230 m base
    assert width == pytest.approx(230.0, abs=10.0)


def test_stereo_report(giza):
    run = json.loads((giza.out_dir / "run.json").read_text())
    stereo = run["chosen"]["stereo"]
    # the bias removed once (0.51 px median while it was removed twice): measured 0.12 px
    assert stereo["vertical_parallax_px"]["median"] <= 0.3 and stereo["vertical_parallax_px"]["n"] >= 100
    assert stereo["affine_residual_px"] < 0.05  # measured 0.007 px over the 800 px crop
    assert stereo["matched_percent"] >= 90.0  # measured 94.7 % of the overlap (70 % with the RPC's height range)
    assert run["inputs"]["kind"] == "satellite pair"
    # searched: the tie points' heights, not the RPC's blind 10..270 m
    low, high = stereo["tie_heights_m"]
    assert all(low - 30 <= t["search_heights_m"][0] and t["search_heights_m"][1] <= high + 30
               for t in stereo["tiles"]["per_tile"])
    dsm = read_raster(giza.out_dir / "dsm.tif").data
    dtm = read_raster(giza.out_dir / "dtm.tif").data
    # products only where both images see the ground: no extrapolation, nothing below the ties
    # (the DSM reached -18 m and the DTM covered the whole grid in streaks)
    assert np.array_equal(np.isfinite(dtm), np.isfinite(dsm))
    assert np.nanmin(dsm) >= low - 10.0 and np.nanmin(dtm) >= low - 10.0
    assert 0.5 < np.isfinite(dsm).mean() < 0.8  # measured 0.69 of the grid


def _fails(args, *needles, tmp_path):
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["-q", "run", *map(str, args), "-o", str(out)])
    assert result.exit_code == 1, result.output
    for n in needles:
        assert n in result.output
    assert not out.exists()


def test_image_without_rpc(tmp_path):
    plain = tmp_path / "plain.tif"
    with rasterio.open(shared(IMG1)) as src:
        profile = src.profile
        data = src.read()
    with rasterio.open(plain, "w", **profile) as dst:
        dst.write(data)
    _fails([plain, shared(IMG2)], "plain.tif", "no RPC", tmp_path=tmp_path)


def test_identical_images(tmp_path):
    _fails([shared(IMG1), shared(IMG1)], "parallax", tmp_path=tmp_path)


def test_crops_that_do_not_overlap(tmp_path):
    far = tmp_path / "img2.tif"
    shutil.copy(shared(IMG2), far)
    shutil.copy(shared("stereo/pleiades_gizeh/img2.geom"), tmp_path / "img2.geom")
    with rasterio.open(far, "r+") as dst:
        t = dst.transform
        dst.transform = rasterio.Affine(t.a, t.b, t.c + 3000, t.d, t.e, t.f)  # 3000 px further east
    _fails([shared(IMG1), far], "img1.tif and", "img2.tif do not overlap", tmp_path=tmp_path)


def test_crops_outside_the_rpc_validity_domain(tmp_path):
    """Crop offsets far beyond the scene the RPCs were fitted on: refused, not extrapolated."""
    paths = []
    for name in ("img1", "img2"):
        moved = tmp_path / f"{name}.tif"
        shutil.copy(shared(f"stereo/pleiades_gizeh/{name}.tif"), moved)
        shutil.copy(shared(f"stereo/pleiades_gizeh/{name}.geom"), tmp_path / f"{name}.geom")
        with rasterio.open(moved, "r+") as dst:
            t = dst.transform
            dst.transform = rasterio.Affine(t.a, t.b, t.c + 200_000, t.d, t.e, t.f - 200_000)
        paths.append(moved)
    _fails(paths, "img1", "outside its RPC validity domain", tmp_path=tmp_path)


def test_absolute_bias_from_control_points(giza, tmp_path):
    """Control points displaced by a known shift: the shift is recovered and applied."""
    from recon3d.core.raster import grid_for_bounds
    from recon3d.core.raster import Raster
    from recon3d.pipeline.run import run
    from recon3d.stereo.satellite import absolute_shift
    from recon3d.terrain.dsm import grid_points

    cloud = giza.cloud
    lo, hi = cloud.bounds
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], 1.0)
    surface = Raster(grid_points(cloud.xyz, transform, shape, reducer="mean"), transform)
    rng = np.random.default_rng(0)
    x, y = surface.cell_centers()
    r = rng.integers(20, shape[0] - 20, 400)
    c = rng.integers(20, shape[1] - 20, 400)
    keep = np.isfinite(surface.data[r, c])
    gcps = np.column_stack([x[c[keep]], y[r[keep]], surface.data[r[keep], c[keep]]])[:60]
    true_shift = np.array([2.0, -1.5, 3.0])
    shift, report = absolute_shift(cloud, gcps + true_shift)
    assert np.abs(shift[:2] - true_shift[:2]).max() <= 0.5  # the search step
    assert abs(shift[2] - true_shift[2]) <= 0.3
    csv = tmp_path / "gcps.csv"
    moved = gcps + true_shift
    csv.write_text("x,y,z\n" + "\n".join(f"{p[0]},{p[1]},{p[2]}" for p in moved) + "\n")
    shifted = run((shared(IMG1), shared(IMG2)), tmp_path / "out", gcps=csv)
    assert shifted.auto["stereo"]["absolute_bias"]["shift_m"] == pytest.approx(shift.tolist(), abs=0.01)
    with pytest.raises(Exception, match="at least 3"):
        absolute_shift(cloud, gcps[:2])


# ------------------------------------------------------------------ tiled rectification
def test_tile_grid_partitions_the_image():
    """Cores cover every pixel once, boxes add the margin; each pixel position is kept by one core."""
    from recon3d.stereo.satellite import _in_core, auto_tile_size, tile_grid

    assert auto_tile_size(800, 801) == 801  # small crops: one tile, as before tiling
    assert auto_tile_size(5000, 3000) == 800
    for width, height, size, margin in [(800, 801, 300, 32), (801, 800, 801, 32), (1000, 37, 64, 10), (5, 7, 2, 3)]:
        cores, boxes = tile_grid(width, height, size, margin)
        count = np.zeros((height, width), int)
        for c0, r0, c1, r1 in cores:
            count[r0:r1, c0:c1] += 1
        assert (count == 1).all()
        assert (cores[:, 2:] - cores[:, :2] <= size).all() and (cores[:, 2:] > cores[:, :2]).all()
        assert (boxes[:, :2] == np.maximum(cores[:, :2] - margin, 0)).all()
        assert (boxes[:, 2:] == np.minimum(cores[:, 2:] + margin, [width, height])).all()
        # row-major order: the first tile at the top left, rows of tiles top to bottom
        assert tuple(cores[0, :2]) == (0, 0) and (np.diff(cores[:, 1]) >= 0).all()
        # sub-pixel positions (as rectified pixels map back) land in exactly one core
        p = np.random.default_rng(0).uniform([0, 0], [width - 1, height - 1], (5000, 2))
        p = np.vstack([p, [[0, 0], [width - 1, height - 1]], cores[:, :2] - 0.5, cores[:, :2] - 0.5 - 1e-9])
        p = p[(p[:, 0] >= 0) & (p[:, 1] >= 0)]
        hits = sum(_in_core(p, core, width, height).astype(int) for core in cores)
        assert (hits == 1).all()
    with pytest.raises(ValueError):
        tile_grid(10, 10, 0)


def _giza_inputs():
    import rasterio as rio

    from recon3d.io.rpc import read_rpc_camera

    cams = [read_rpc_camera(shared(p)) for p in (IMG1, IMG2)]
    images = []
    for cam in cams:
        with rio.open(cam.image_path) as src:
            images.append(src.read(1, masked=True).astype(np.float32).filled(np.nan))
    return cams, images


@pytest.fixture(scope="module")
def giza_tiled():
    """The Giza pair in 300 px tiles (9 tiles, 32 px margins), straight from dense_cloud_rpc."""
    from recon3d.stereo.satellite import dense_cloud_rpc

    (a, b), images = _giza_inputs()
    return dense_cloud_rpc(a, b, *images, tile_size=300)


def test_tiled_giza_keeps_the_pyramid(giza_tiled, giza):
    from recon3d.terrain.dsm import grid_points, make_dsm

    cloud, report = giza_tiled
    tiles = report["tiles"]
    assert tiles["count"] == 9 and tiles["failed"] == 0 and len(tiles["per_tile"]) == 9
    for t in tiles["per_tile"]:  # measured: medians 0.10-0.18 px, p90 at most 0.62 px
        assert t["vertical_parallax_px"]["median"] < 0.5 and t["vertical_parallax_px"]["p90"] < 1.0, t
        assert t["vertical_parallax_px"]["n"] >= 50, t
        assert t["affine_residual_px"] < 0.05, t
        assert t["bias_from"] == "tie points"
        assert t["points"] > 0
    assert report["vertical_parallax_px"]["median"] < 0.3 and report["vertical_parallax_px"]["p90"] < 1.0
    assert sum(t["points"] for t in tiles["per_tile"]) == report["points"] == len(cloud)
    # the overlap margins add 47 % of matched pixels: points kept by two tiles would show
    single = giza.auto["stereo"]
    assert single["tiles"]["count"] == 1  # an 800 px crop is one tile by default
    assert report["points"] == pytest.approx(single["points"], rel=0.02)
    assert cloud.crs.to_epsg() == 32636
    reference = read_raster(giza.out_dir / "dsm.tif")
    dsm = make_dsm(cloud, reference.resolution, max_hole_cells=200, rim="low")
    _, _, width = _pyramid(dsm)
    assert width == pytest.approx(230.0, abs=10.0)
    # the summit platform: median of the cells within 3 m of the centre (the single
    # highest cells are matching spikes that move with every matcher change; measured
    # 137.7 m in one tile, 138.1 m in 300 px tiles)
    e, n = pyproj.Transformer.from_crs(4326, dsm.crs, always_xy=True).transform(*KHUFU)
    x, y = dsm.cell_centers()
    gx, gy = np.meshgrid(x, y)
    ring = np.maximum(np.abs(gx - e), np.abs(gy - n))
    base = np.nanmedian(np.where((ring > 118) & (ring < 130), dsm.data, np.nan))
    summit = np.nanmedian(dsm.data[np.hypot(gx - e, gy - n) < 3.0]) - base
    assert summit == pytest.approx(139.0, abs=3.0)
    # the same surface as one tile: no offset between tiles, matching noise only
    tiled = grid_points(cloud.xyz, reference.transform, reference.data.shape, reducer="mean")
    single = grid_points(giza.cloud.xyz, reference.transform, reference.data.shape, reducer="mean")
    diff = (tiled - single)[np.isfinite(tiled) & np.isfinite(single)]
    assert diff.size > 0.8 * np.isfinite(single).sum()
    assert abs(np.median(diff)) < 0.2 and np.median(np.abs(diff)) < 1.0  # measured 0.05 m and 0.51 m


def test_tiles_skip_empty_areas_and_repeat_exactly():
    """A crop with a no-data quadrant: its tile is skipped and counted; two runs give the same bytes."""
    import dataclasses

    from recon3d.errors import InputError
    from recon3d.stereo.satellite import dense_cloud_rpc

    (a, b), (image_a, image_b) = _giza_inputs()
    sub = dataclasses.replace(a, width=360, height=360, col0=a.col0 + 200, row0=a.row0 + 200)
    crop = image_a[200:560, 200:560].copy()
    crop[:190, :190] = np.nan  # the first tile's core and 94 % of its box
    # the second image cut around it: each must see at least 20 % of the other
    b = dataclasses.replace(b, width=600, height=600, col0=b.col0 + 100, row0=b.row0 + 100)
    image_b = image_b[100:700, 100:700]
    runs = [dense_cloud_rpc(sub, b, crop, image_b, tile_size=180, margin=16) for _ in range(2)]
    (c1, r1), (c2, r2) = runs
    assert r1["tiles"]["count"] == 4 and r1["tiles"]["failed"] == 1
    assert r1["tiles"]["failures"][0]["tile"] == 0 and "no texture" in r1["tiles"]["failures"][0]["reason"]
    assert [t["tile"] for t in r1["tiles"]["per_tile"]] == [1, 2, 3]
    assert c1.xyz.tobytes() == c2.xyz.tobytes() and json.dumps(r1) == json.dumps(r2)
    with pytest.raises(InputError, match="too few to bound the heights"):
        dense_cloud_rpc(sub, b, np.full_like(crop, np.nan), image_b, tile_size=180)
