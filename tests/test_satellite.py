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


def test_dsm_in_utm_with_the_pyramid(giza):
    dsm = read_raster(giza.out_dir / "dsm.tif")
    assert dsm.crs.to_epsg() == 32636  # chosen from the scene centre
    e, n = pyproj.Transformer.from_crs(4326, 32636, always_xy=True).transform(*KHUFU)
    x, y = dsm.cell_centers()
    gx, gy = np.meshgrid(x, y)
    z = dsm.data
    near = np.hypot(gx - e, gy - n) < 60
    iy, ix = np.unravel_index(np.nanargmax(np.where(near, z, -np.inf)), z.shape)
    apex = z[iy, ix]
    ring = np.maximum(np.abs(gx - gx[iy, ix]), np.abs(gy - gy[iy, ix]))
    base = np.nanmedian(np.where((ring > 118) & (ring < 130), z, np.nan))  # just outside the 230 m base
    # the summit's cells scatter by +-3 m (stepped masonry, matching noise): the single
    # highest cell gives 142.1 m, the mean of the five highest 140.2 m (issue: 139 +- 3)
    top5 = np.sort(z[near & np.isfinite(z)])[-5:].mean()
    assert apex - base == pytest.approx(139.0, abs=3.5)
    assert top5 - base == pytest.approx(139.0, abs=3.0)
    above = np.nan_to_num(z[iy], nan=-1e9) > base + 2  # the base along the east-west line through the apex
    lo = hi = ix
    while lo > 0 and above[lo - 1]:
        lo -= 1
    while hi < len(above) - 1 and above[hi + 1]:
        hi += 1
    assert (hi - lo) * dsm.resolution == pytest.approx(230.0, abs=10.0)  # measured 235 m (228 m north-south)


def test_stereo_report(giza):
    run = json.loads((giza.out_dir / "run.json").read_text())
    stereo = run["chosen"]["stereo"]
    assert stereo["vertical_parallax_px"]["median"] <= 1.0 and stereo["vertical_parallax_px"]["n"] >= 100
    assert stereo["matched_percent"] >= 70.0
    assert run["inputs"]["kind"] == "satellite pair"
    smooth = read_raster(giza.out_dir / "dtm.tif").data
    assert np.isfinite(smooth).all()


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
    _fails([shared(IMG1), far], "img1 and img2", "do not overlap", tmp_path=tmp_path)


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
