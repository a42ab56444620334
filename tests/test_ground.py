"""Ground filters and the DTM on the real LiDAR files, measured against the providers' classes.

Targets (issue: terrain): total error at or below a per-file oracle-tuned Cloth
Simulation Filter (0.31 % Delft, 0.20 % IGN village), DTM RMS <= 0.15 m against the
DTM interpolated from the provider's ground points, works on stereo-like surfaces,
tilted terrain and units in feet.
"""

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import ndimage

from conftest import AUTZEN, DELFT, IGN, shared
from recon3d.config import GroundConfig
from recon3d.core.geo import crs_units, parse_crs
from recon3d.core.pointcloud import PointCloud
from recon3d.errors import InputError
from recon3d.io.las import read_las
from recon3d.quality.evaluate import ground_filter_errors
from recon3d.terrain import dsm as dsm_stage
from recon3d.terrain import dtm as dtm_stage
from recon3d.terrain.ground import classify_ground

FILES = {"delft": (DELFT, "EPSG:7415"), "ign": (IGN, None), "autzen": (AUTZEN, None)}
#: Total error (%) of CSF tuned per file on the reference (an optimistic oracle); Autzen has no object class.
ORACLE_CSF = {"delft": 0.31, "ign": 0.20, "autzen": 2.54}


@pytest.fixture(scope="module", params=list(FILES))
def lidar(request):
    path, crs = FILES[request.param]
    cloud = read_las(shared(path), crs=parse_crs(crs) if crs else None)
    units = crs_units(cloud.crs)
    res, _ = dsm_stage.choose_resolution(dsm_stage.point_spacing(cloud.xyz[:, :2]), units)
    grid = dsm_stage.make_dsm(cloud, res, max_hole_cells=int(units.area(25) / res**2))
    ref_dtm = dtm_stage.make_dtm(cloud.xyz[cloud.classification == 2], grid)
    return request.param, cloud, units, grid, ref_dtm


def _dtm_rms(result, cloud, units, grid, ref_dtm):
    noise = result.params["noise"]["value"] / units.vertical
    dtm = dtm_stage.make_dtm(cloud.xyz[result.for_dtm], grid, noise=noise)
    covered = np.isfinite(grid.data)
    return float(np.sqrt(np.mean(((dtm.data - ref_dtm.data)[covered] * units.vertical) ** 2)))


def test_automatic_filter_beats_oracle_csf(lidar):
    name, cloud, units, grid, ref_dtm = lidar
    result = classify_ground(cloud, GroundConfig(), units, grid.resolution)
    errors = ground_filter_errors(result.is_ground, cloud.classification)
    assert errors["total_percent"] <= ORACLE_CSF[name]
    assert _dtm_rms(result, cloud, units, grid, ref_dtm) <= 0.15
    assert result.params["method"]["value"] == "smrf"  # LiDAR: return numbers present
    for key in ("cell", "max_window", "slope", "noise", "threshold"):
        assert result.params[key]["reason"]


@pytest.mark.parametrize("method", ["smrf", "tophat", "drape"])
def test_every_method_works_on_lidar(lidar, method):
    name, cloud, units, grid, ref_dtm = lidar
    result = classify_ground(cloud, GroundConfig(method=method), units, grid.resolution)
    errors = ground_filter_errors(result.is_ground, cloud.classification)
    assert errors["total_percent"] <= (3.0 if name == "autzen" else 1.0)
    assert _dtm_rms(result, cloud, units, grid, ref_dtm) <= 0.35


def _stereo_like(cloud, grid, units, noise_m, seed=1):
    """The LiDAR DSM as a stereo matcher would give it: one point per cell, noisy, holed, no returns."""
    rng = np.random.default_rng(seed)
    holes = ndimage.binary_dilation(rng.random(grid.shape) < 0.01, iterations=3)
    x, y = grid.cell_centers()
    gx, gy = np.meshgrid(x, y)
    ok = np.isfinite(grid.data) & ~holes
    z = grid.data[ok] + rng.normal(0, units.height(noise_m), ok.sum())
    return PointCloud(np.column_stack([gx[ok], gy[ok], z]), {}, cloud.crs)


def test_stereo_like_surface(lidar):
    """0.3 m noise, 1 % of cells starting 7-cell holes: the DTM stays within a few decimetres."""
    name, cloud, units, grid, ref_dtm = lidar
    stereo = _stereo_like(cloud, grid, units, 0.3)
    result = classify_ground(stereo, GroundConfig(), units, grid.resolution)
    assert result.params["method"]["value"] == "tophat"
    assert 0.2 <= result.params["noise"]["value"] <= 0.5  # measured, not given
    rms = _dtm_rms(result, stereo, units, grid, ref_dtm)
    # measured: ign 0.21, delft 0.39, autzen 0.91 (5 ft cells; dense vegetation)
    assert rms <= {"ign": 0.3, "delft": 0.5, "autzen": 1.0}[name]


def test_clean_surface_without_returns_is_filtered_with_smrf(lidar):
    """0.1 m of noise and no return numbers: SMRF, whose DTM is within a few decimetres."""
    name, cloud, units, grid, ref_dtm = lidar
    stereo = _stereo_like(cloud, grid, units, 0.1)
    result = classify_ground(stereo, GroundConfig(), units, grid.resolution)
    assert result.params["method"]["value"] == "smrf" and "noise" in result.params["method"]["reason"]
    # measured: ign 0.075, delft 0.19, autzen 0.66 (top-hat: 0.088, 0.28, 0.58)
    assert _dtm_rms(result, stereo, units, grid, ref_dtm) <= {"ign": 0.1, "delft": 0.25, "autzen": 0.75}[name]


@pytest.mark.parametrize("tilt", [0.3, 1.0])
def test_steep_terrain_keeps_buildings_off_the_ground(tilt):
    """The IGN village on a 30 % and a 45-degree slope: roofs must not become ground."""
    cloud = read_las(shared(IGN))
    units = crs_units(cloud.crs)
    xyz = cloud.xyz.copy()
    xyz[:, 2] += tilt * (xyz[:, 0] - xyz[:, 0].min())
    tilted = PointCloud(xyz, cloud.attributes, cloud.crs)
    result = classify_ground(tilted, GroundConfig(), units, 0.5)
    c = cloud.classification
    assert np.mean(result.is_ground[c == 6]) <= 0.005
    assert np.mean(~result.is_ground[c == 2]) <= 0.005


def test_rooftop_only_and_tiny_clouds():
    cloud = read_las(shared(DELFT), crs=parse_crs("EPSG:7415"))
    units = crs_units(cloud.crs)
    roofs = cloud[cloud.classification == 6]
    result = classify_ground(roofs, GroundConfig(), units, 0.5)
    assert result.is_ground.any() and np.isfinite(result.terrain.data).all()
    with pytest.raises(InputError, match="at least 3"):
        classify_ground(cloud[:1], GroundConfig(), units, 0.5)
    grid = dsm_stage.make_dsm(cloud, 0.5, max_hole_cells=100)
    with pytest.raises(InputError, match="only 2 ground points"):
        dtm_stage.make_dtm(cloud.xyz[:2], grid)


def test_breaklines_and_spot_heights_are_honoured():
    cloud = read_las(shared(IGN))
    grid = dsm_stage.make_dsm(cloud, 0.5, max_hole_cells=100)
    ground = cloud.xyz[cloud.classification == 2]
    free = dtm_stage.make_dtm(ground, grid)
    lo, hi = cloud.bounds
    x = np.linspace(lo[0] + 10, hi[0] - 10, 5)
    y = np.full(5, (lo[1] + hi[1]) / 2)
    line = np.column_stack([x, y, free.sample(x, y) + 1.0])  # a 1 m embankment crest
    spot = np.array([[lo[0] + 20, lo[1] + 10, free.sample([lo[0] + 20], [lo[1] + 10])[0] - 0.7]])
    constraints = np.concatenate([dtm_stage.densify_lines([line], grid.resolution / 2), spot])
    dtm = dtm_stage.make_dtm(ground, grid, constraints=constraints)
    on = dtm.sample(constraints[:, 0], constraints[:, 1], bilinear=False)
    # each cell holding constraints takes their mean: exact to the slope within half a cell
    assert np.abs(on - constraints[:, 2]).max() <= 0.05
    far = np.abs(grid.cell_centers()[1] - y[0]) > 5
    away = np.ones(grid.shape, bool)
    away[~far] = False
    assert np.abs(dtm.data - free.data)[away].max() <= 0.75  # the spot height only moves its cell


def test_evaluate_ground_command(tmp_path, delft_run):
    from recon3d.cli import cli

    result = CliRunner().invoke(
        cli,
        ["evaluate", "ground", str(delft_run.out_dir / "cloud.laz"), "--reference", str(shared(DELFT)),
         "--crs", "EPSG:7415", "--json", str(tmp_path / "g.json")],
    )
    assert result.exit_code == 0, result.output
    import json

    numbers = json.loads((tmp_path / "g.json").read_text())
    assert numbers["points"]["total_percent"] <= 0.31 and numbers["points"]["kappa"] >= 0.99
    dtm_vs_dtm = next(t for t in numbers["accuracy"] if t["reference"] == "DTM from provider ground points")
    assert dtm_vs_dtm["rms"] <= 0.15
    from recon3d.io.las import write_las

    shifted = delft_run.cloud.with_attribute("classification", delft_run.reference_classes)
    shifted = PointCloud(shifted.xyz + [5.0, 0.0, 0.0], shifted.attributes, shifted.crs)
    write_las(shifted, tmp_path / "shifted.laz")
    bad = CliRunner().invoke(
        cli, ["evaluate", "ground", str(delft_run.out_dir / "cloud.laz"), "--reference", str(tmp_path / "shifted.laz")]
    )
    assert bad.exit_code == 1 and "not the same points" in bad.output
    other_crs = CliRunner().invoke(
        cli, ["evaluate", "ground", str(delft_run.out_dir / "cloud.laz"), "--reference", str(shared(IGN))]
    )
    assert other_crs.exit_code == 1 and "EPSG:7415" in other_crs.output


def test_gap_fill_reproduces_a_plane_under_building_sized_gaps():
    """Linear interpolation is exact on a plane: every gap inside the rims' hull gets it back."""
    rows, cols = np.indices((300, 240), dtype=np.float64)
    plane = 0.03 * rows - 0.02 * cols + 5.0
    known = np.ones(plane.shape, bool)
    rng = np.random.default_rng(3)
    for r, c, h, w in zip(rng.integers(5, 270, 40), rng.integers(5, 210, 40), rng.integers(3, 25, 40),
                          rng.integers(3, 25, 40), strict=True):
        known[r:r + h, c:c + w] = False  # larger than the gaps the neighbour mean fills
    filled = dtm_stage.fill_gaps(np.where(known, plane, np.nan), known)
    assert np.abs(filled - plane).max() < 1e-9


def test_gap_fill_is_the_same_in_small_batches(monkeypatch):
    """The triangles are rasterised a batch of triangles, rows and cells at a time (memory
    bounded on survey-sized grids): batches of a few give the same bytes as the default; a gap
    of one cell takes the mean of its known neighbours."""
    rows, cols = np.indices((200, 160), dtype=np.float64)
    rng = np.random.default_rng(5)
    surface = 0.03 * rows - 0.02 * cols + 5.0 + rng.normal(0.0, 0.1, rows.shape)
    known = rng.random(rows.shape) > 0.2  # many gaps of 1-4 cells
    for r, c, h, w in zip(rng.integers(5, 170, 12), rng.integers(5, 130, 12), rng.integers(5, 30, 12),
                          rng.integers(5, 30, 12), strict=True):
        known[r:r + h, c:c + w] = False
    known[99:102, 99:102] = True
    known[100, 100] = False
    values = np.where(known, surface, np.nan)
    whole = dtm_stage.fill_gaps(values, known)
    monkeypatch.setattr(dtm_stage, "ROW_CHUNK", 7)
    monkeypatch.setattr(dtm_stage, "RASTER_CHUNK", 50)
    monkeypatch.setattr(dtm_stage, "TRIANGLE_CHUNK", 13)
    assert np.array_equal(dtm_stage.fill_gaps(values, known), whole)
    assert np.isfinite(whole).all()
    ring = surface[99:102, 99:102].copy()
    ring[1, 1] = np.nan
    assert whole[100, 100] == pytest.approx(np.nanmean(ring), abs=1e-12)


def test_gap_fill_interpolates_a_bay_reaching_the_border():
    """A gap 100 cells deep along the border, closed by one column of ground, is interpolated
    (no cell falls back to the nearest known value)."""
    rows, cols = np.indices((200, 200), dtype=np.float64)
    plane = 0.1 * rows + 0.05 * cols
    known = np.ones(plane.shape, bool)
    known[60:140, 100:] = False  # a bay open to the right border
    known[:, 199] = True  # closed by a last column: the hull spans the bay
    filled = dtm_stage.fill_gaps(np.where(known, plane, np.nan), known)
    assert np.abs(filled - plane).max() < 1e-9


def test_a_hole_filled_low_on_a_slope_is_raised_to_the_terrain():
    """A stereo DSM's hole on a 10 % slope takes its rim's low side (up to 2 m below the
    ground); raised to the DTM interpolated under it, it is back on the slope. Cells
    above the DTM and nodata stay as they were."""
    from affine import Affine

    from recon3d.core.raster import Raster

    rows, cols = np.indices((120, 120), dtype=np.float64)
    ground = 0.1 * 0.5 * rows + 20.0  # 0.5 m cells, rising 10 % along the rows
    surface = ground.copy()
    surface[10:30, 10:30] += 12.0  # a roof
    surface[0, :5] = np.nan
    known = np.ones(ground.shape, bool)
    known[60:100, 40:80] = False  # a 20 x 20 m hole
    dsm = dsm_stage.fill_small_holes(np.where(known, surface, np.nan), 2000, rim="low")
    assert (dsm - ground)[~known].min() < -1.9  # the rim's low side
    grid = Raster(dsm, Affine(0.5, 0, 0, 0, -0.5, 60.0), None)
    on_ground = known & np.isfinite(surface) & (surface == ground)
    dtm = dtm_stage.dtm_from_cells(np.where(on_ground, ground, np.nan), on_ground.astype(float), grid)
    before = grid.data.copy()
    lift = dtm_stage.raise_to_terrain(grid, dtm)
    assert np.abs(grid.data - ground)[~known].max() < 1e-4
    assert np.allclose(lift[~known], (ground - before)[~known].clip(min=0), atol=1e-4)
    assert (lift[~known] > 0).mean() > 0.45 and not lift[known & np.isfinite(before)].any()
    assert np.array_equal(np.isnan(grid.data), np.isnan(before))
    assert np.array_equal(grid.data[10:30, 10:30], before[10:30, 10:30])


def test_gap_fill_holdout_on_provider_ground(lidar):
    """Ground cells hidden in building-sized blobs come back within the terrain's own relief
    (gap RMS measured before the OpenCV triangulation: Delft 0.068 m, IGN 0.091 m, Autzen 0.96 ft)."""
    name, cloud, units, grid, _ = lidar
    mean = dsm_stage.grid_points(cloud.xyz[cloud.classification == 2], grid.transform, grid.shape, reducer="mean")
    known = np.isfinite(mean)
    rng = np.random.default_rng(1)
    seeds = np.zeros(known.shape, bool)
    seeds.ravel()[rng.choice(known.size, known.size // 400, replace=False)] = True
    hidden = ndimage.binary_dilation(seeds, iterations=6) & known
    filled = dtm_stage.fill_gaps(mean, known & ~hidden)
    rms = float(np.sqrt(np.mean((filled[hidden] - mean[hidden]) ** 2))) * units.vertical
    assert rms < {"delft": 0.08, "ign": 0.11, "autzen": 0.33}[name]



def test_fill_pits_raises_narrow_hollows_only():
    """A 10 m wide, 5 m deep pit in a 5 % slope is raised to the slope; a 1.5 m dip is
    left as it is, and so is the slope; an 80 m wide, 6 m deep basin keeps its floor
    (the square window rounds its rim, where it does not fit inside: a limit of the
    closing, said in PIT_WIDTH's comment)."""
    from affine import Affine

    from recon3d.core.raster import Raster
    from recon3d.terrain.ground import fill_pits

    y, x = np.mgrid[0:200, 0:200] * 1.0
    plane = 100.0 + 0.05 * x
    z = plane.copy()
    pit = (np.abs(x - 50) < 5) & (np.abs(y - 50) < 5)
    z[pit] -= 5.0
    dip = (np.abs(x - 50) < 5) & (np.abs(y - 150) < 5)
    z[dip] -= 1.5
    basin = np.hypot(x - 140, y - 100) < 40
    z[basin] -= 6.0
    terrain = Raster(z, Affine(1.0, 0.0, 0.0, 0.0, -1.0, 200.0), None)
    out, raised = fill_pits(terrain, width=30.0, depth=2.0)
    assert np.abs(out.data[pit] - plane[pit]).max() <= 0.5
    floor = np.hypot(x - 140, y - 100) < 18
    changed = out.data != terrain.data  # (the raster keeps float32 heights)
    assert not changed[dip].any() and not changed[floor].any()
    assert raised == changed.sum() and not changed[~(pit | basin)].any()
    flat, none = fill_pits(Raster(plane, terrain.transform, None), width=30.0, depth=2.0)
    assert none == 0 and np.array_equal(flat.data, plane.astype(flat.data.dtype))



def test_a_roof_at_the_corner_of_the_data_does_not_raise_the_terrain():
    """A frame-stereo grid is mostly cells outside the data, filled from their nearest
    measured cell: a roof at a corner of the data is copied over the whole quarter of
    the grid beyond it, a plateau far wider than any opening, which the trend took for
    terrain (up to 6.6 m above the flat ground, 2 m at the 95th percentile) and so did
    SMRF's openings (the roof itself, and 7.5 m on the ground beside it). Both look at
    the measured cells only, where the roof is 16 m across."""
    from affine import Affine

    from recon3d.core.geo import Units
    from recon3d.terrain.ground import minimum_surface, smrf_terrain

    rows, cols = np.indices((100, 150), dtype=np.float64)
    data = (rows >= 60) & (cols >= 60) & (np.random.default_rng(0).random(rows.shape) < 0.5)
    roof = (rows >= 60) & (rows < 76) & (cols >= 60) & (cols < 76)
    zmin = np.where(data, np.where(roof, 15.0, 0.0), np.nan)
    surface = minimum_surface(zmin, Affine(1, 0, 0, 0, -1, 100), GroundConfig(max_window=30), Units(), {})
    assert np.abs(surface.trend[data & ~roof]).max() <= 0.05
    assert np.abs(smrf_terrain(surface, Units()).data[data]).max() <= 0.05


def test_a_pit_at_the_corner_of_the_data_is_filled():
    """Mismatches 6 m under the ground at a corner of a frame-stereo survey's data,
    copied by the nearest-cell fill over the quarter of the grid beyond: a basin open
    to the border, which a closing of the whole grid leaves as it is. The closing of
    the measured cells raises it to the ground around."""
    from affine import Affine

    from recon3d.core.raster import Raster
    from recon3d.terrain.dtm import fill_nearest
    from recon3d.terrain.ground import fill_pits

    rows, cols = np.indices((100, 150), dtype=np.float64)
    data = (rows >= 60) & (cols >= 60) & (np.random.default_rng(0).random(rows.shape) < 0.5)
    pit = data & (rows < 66) & (cols < 66)
    terrain = Raster(fill_nearest(np.where(data, np.where(pit, -6.0, 0.0), np.nan)), Affine(1, 0, 0, 0, -1, 100))
    assert fill_pits(terrain, 30.0, 2.0)[1] == 0
    filled, raised = fill_pits(terrain, 30.0, 2.0, data)
    assert raised >= pit.sum() and np.abs(filled.data[data]).max() <= 1e-6
