"""A survey delivered as LAS/LAZ tiles: files, a folder or a glob read as one cloud, the
same products byte for byte as the whole file, and the bad tile sets refused."""

import hashlib
import subprocess
import sys

import laspy
import numpy as np
import pytest
from conftest import DELFT, IGN, shared

#: Products compared byte for byte (run.json and the reports name their inputs).
PRODUCTS = ("dsm.tif", "dtm.tif", "ndsm.tif", "model_dsm.tif", "cloud.laz", "buildings.city.json",
            "buildings.obj", "buildings.glb", "buildings_3dtiles/tileset.json", "buildings_3dtiles/tiles/0_0_0.glb",
            "footprints.geojson", "footprints.gpkg")


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "recon3d", "-q", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    """The IGN village cut into 4 quadrant tiles (LAZ), and the tile folder."""
    folder = tmp_path_factory.mktemp("tiles") / "ign"
    folder.mkdir()
    las = laspy.read(shared(IGN))
    mx, my = np.median(las.x), np.median(las.y)
    west, south = np.asarray(las.x) < mx, np.asarray(las.y) < my
    for name, mask in (("sw", west & south), ("se", ~west & south), ("nw", west & ~south), ("ne", ~west & ~south)):
        tile = laspy.LasData(las.header)
        tile.points = las.points[mask]
        tile.write(folder / f"ign_{name}.laz")
    return folder


def test_tiles_give_the_products_of_the_whole_file(tiles, ign_run, tmp_path):
    whole = ign_run.out_dir
    for label, args in (("glob", [str(tiles / "*.laz")]), ("folder", [tiles]),
                        ("files in another order", sorted(tiles.glob("*.laz"), reverse=True))):
        out = tmp_path / label.replace(" ", "_")
        result = _cli("run", *args, "-o", out, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        for name in PRODUCTS:
            assert _sha(out / name) == _sha(whole / name), f"{label}: {name} differs"
    import json

    record = json.loads((tmp_path / "glob" / "run.json").read_text())
    assert record["inputs"]["kind"] == "point cloud in 4 tiles" and len(record["inputs"]["tiles"]) == 4
    assert record["inputs"]["points"] == len(ign_run.cloud)


def _refused(result, *needles):
    assert result.returncode == 1, result.stderr
    line, = result.stderr.strip().splitlines()
    assert line.startswith("recon3d: error: ") and "Traceback" not in result.stderr
    for n in needles:
        assert n in line, line


def test_bad_tile_sets(tiles, tmp_path):
    import shutil

    import pyproj

    def tile_set(name):
        folder = tmp_path / name
        shutil.copytree(tiles, folder)
        return folder

    dup = tile_set("dup")
    shutil.copy(dup / "ign_sw.laz", dup / "copy_of_sw.laz")
    _refused(_cli("run", dup, "-o", tmp_path / "o1", cwd=tmp_path), "the same tile as", "give it once")
    other = tile_set("crs")
    las = laspy.read(other / "ign_ne.laz")
    header = laspy.LasHeader(point_format=las.header.point_format, version=las.header.version)
    header.scales, header.offsets = las.header.scales, las.header.offsets
    header.add_crs(pyproj.CRS("EPSG:32631"))
    moved = laspy.LasData(header)
    moved.points = las.points
    moved.write(other / "ign_ne.laz")
    _refused(_cli("run", other, "-o", tmp_path / "o2", cwd=tmp_path), "ign_ne.laz")
    broken = tile_set("broken")
    data = (broken / "ign_se.laz").read_bytes()
    (broken / "ign_se.laz").write_bytes(data[: len(data) // 3])
    _refused(_cli("run", broken, "-o", tmp_path / "o3", cwd=tmp_path), "ign_se.laz")
    _refused(_cli("run", str(tmp_path / "nothing" / "*.laz"), "-o", tmp_path / "o4", cwd=tmp_path),
             "no LAS/LAZ file matches")
    _refused(_cli("run", tiles / "ign_sw.laz", shared("citymodels/multi_lod.json"), "-o", tmp_path / "o5",
                  cwd=tmp_path), "not a LAS/LAZ tile")
    assert not any((tmp_path / f"o{k}").exists() for k in range(1, 6))


def test_overlapping_tiles_keep_each_point_once(tiles, ign_run, tmp_path):
    """Tiles delivered with buffers hold the points of the overlap twice: kept once, warned of."""
    import json
    import shutil

    folder = tmp_path / "buffered"
    shutil.copytree(tiles, folder)
    las = laspy.read(shared(IGN))
    mx = np.median(las.x)
    band = laspy.LasData(las.header)
    band.points = las.points[np.abs(np.asarray(las.x) - mx) < 5.0]  # a 10 m strip across two tiles
    band.write(folder / "buffer.laz")
    out = tmp_path / "out"
    result = _cli("run", folder, "-o", out, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    record = json.loads((out / "run.json").read_text())
    assert any(f"{len(band.points)} points are in two overlapping tiles" in w for w in record["warnings"])
    assert _sha(out / "dsm.tif") == _sha(ign_run.out_dir / "dsm.tif")
    assert _sha(out / "cloud.laz") == _sha(ign_run.out_dir / "cloud.laz")


# --------------------------------------------------------------------------- work tiles


#: Every product whose bytes must not depend on the tiling (run.json names the tiling).
ALL_PRODUCTS = (*PRODUCTS, "report.json")


def _same_products(a, b, label):
    for name in ALL_PRODUCTS:
        assert _sha(a / name) == _sha(b / name), f"{label}: {name} differs"


def test_tile_grid_covers_every_cell_once_in_morton_order():
    from recon3d.pipeline.tiling import BLOCK, TileGrid, morton

    grid = TileGrid((300, 520), BLOCK * 2, 10)
    tiles = grid.tiles()
    owner = np.zeros((300, 520), int)
    for t in tiles:
        owner[t.rows, t.cols] += 1
    assert np.all(owner == 1)
    codes = [int(morton(np.array([t.key[0]]), np.array([t.key[1]]))[0]) for t in tiles]
    assert codes == sorted(codes)
    # an aligned square of blocks is one run of Morton codes: cloud.laz's order is the tiles' order
    r, c = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    inner = morton(r[2:4, 4:6].ravel(), c[2:4, 4:6].ravel())
    assert np.ptp(inner) == len(inner) - 1
    rows, cols = grid.tiles()[0].window(10, grid.shape)
    assert (rows.start, cols.start) == (0, 0) and rows.stop == BLOCK * 2 + 10


def test_window_sampling_gives_the_whole_grids_values():
    """A window of a raster samples world points (bilinear and nearest) to the bit as the
    whole raster does, also at cell edges, where a shifted transform would round otherwise."""
    from affine import Affine

    from recon3d.core.raster import Raster

    rng = np.random.default_rng(0)
    whole = Raster(rng.normal(size=(200, 300)).astype(np.float32), Affine(0.1, 0, 84999.95, 0, -0.1, 447650.05))
    window = whole.window(slice(37, 150), slice(91, 260))
    x = rng.uniform(84999.95 + 93 * 0.1, 84999.95 + 257 * 0.1, 20000)
    y = rng.uniform(447650.05 - 147 * 0.1, 447650.05 - 40 * 0.1, 20000)
    x[:5000] = 84999.95 + rng.integers(93, 257, 5000) * 0.1  # exactly on cell edges
    for bilinear in (True, False):
        assert np.array_equal(whole.sample(x, y, bilinear=bilinear), window.sample(x, y, bilinear=bilinear))
    row, col = whole.rowcol(x, y)
    wrow, wcol = window.rowcol(x, y)
    assert np.array_equal(row - 37, wrow) and np.array_equal(col - 91, wcol)


def test_point_store_reads_tiles_in_survey_order(tmp_path):
    from recon3d.io.las import read_las
    from recon3d.pipeline.points import LasStore, cell_rowcol

    store = LasStore([shared(IGN)], tmp_path / "buckets")
    whole = read_las(shared(IGN))
    assert store.summary.count == len(whole) and np.array_equal(store.summary.bounds, whole.bounds)
    from recon3d.core.raster import grid_for_bounds

    lo, hi = whole.bounds
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], 0.5)
    row, col = cell_rowcol(whole.xyz, transform)
    halves = [store.read(slice(0, shape[0]), cols, transform) for cols in (slice(0, 90), slice(90, shape[1]))]
    assert sum(len(h) for h in halves) == len(whole)
    for h, cols in zip(halves, (slice(0, 90), slice(90, shape[1])), strict=True):
        mine = (col >= cols.start) & (col < cols.stop)
        assert np.array_equal(h.order, np.flatnonzero(mine))  # every point once, in file order
        assert np.array_equal(h.cloud.xyz, whole.xyz[mine])
        assert np.array_equal(h.cloud.classification, whole.classification[mine])


def test_sorting_on_the_deciding_keys_first_is_lexsort():
    """cloud.laz's point order: the tie-resolving sort gives np.lexsort's order, with many
    ties in the deciding keys, NaN in the others, and NaN in a deciding key (which falls
    back to np.lexsort)."""
    from recon3d.pipeline.points import lexsort_ties

    rng = np.random.default_rng(7)
    for trial in range(500):
        n, level = int(rng.integers(0, 80)), int(rng.integers(1, 5))
        keys = [rng.integers(0, level + 1, n).astype(np.uint16), np.round(rng.random(n) * level) / 2,
                *(rng.integers(0, level, n).astype(float) for _ in range(3)), rng.integers(0, level, n)]
        keys[1][rng.random(n) < 0.2] = np.nan
        if trial % 10 == 0 and n:
            keys[3][0] = np.nan
        np.testing.assert_array_equal(lexsort_ties(keys, 3), np.lexsort(keys))


def test_points_per_metre_of_height_are_counted_as_unique_counts_them():
    """The histogram of heights behind the gross-error median: counted where the heights
    span few metres, sorted where a gross error stretches them; np.unique's answer either way."""
    from recon3d.pipeline.points import _metre_counts

    rng = np.random.default_rng(3)
    for z in (rng.normal(-3.0, 4.0, 5000), np.r_[rng.normal(20.0, 5.0, 50), 1e7, -2e6], np.array([-0.5])):
        keys, counts = _metre_counts(z)
        want_keys, want_counts = np.unique(np.floor(z).astype(np.int64), return_counts=True)
        np.testing.assert_array_equal(keys, want_keys)
        np.testing.assert_array_equal(counts, want_counts)


@pytest.mark.parametrize("collide", [False, True])
def test_repeats_of_overlapping_tiles_are_found_exactly(collide, monkeypatch):
    """A point is a repeat when one earlier in the survey has the same x, y, z and GPS
    time (0.0 and -0.0 alike, NaN never): the coded sort finds the same repeats as a
    comparison of every pair, also when every point gets the same code."""
    from recon3d.pipeline import points

    if collide:
        monkeypatch.setattr(points, "_point_code", lambda keys: np.zeros(len(keys[0]), np.uint64))
    rng = np.random.default_rng(11)
    dtype = np.dtype([("x", "f8"), ("y", "f8"), ("z", "f8"), ("gps_time", "f8"), ("order", "i8")])
    for _ in range(30):
        n = int(rng.integers(1, 120))
        rec = np.zeros(n, dtype)
        for name in ("x", "y", "z", "gps_time"):
            rec[name] = rng.integers(-1, 2, n) * 0.5
        rec["x"][rng.random(n) < 0.1] = -0.0
        rec["gps_time"][rng.random(n) < 0.1] = np.nan
        rec["order"] = rng.permutation(n)
        rows = np.column_stack([rec[k] for k in ("x", "y", "z", "gps_time")])
        same = (rows[:, None] == rows[None, :]).all(axis=2)
        earlier = rec["order"][None, :] < rec["order"][:, None]
        np.testing.assert_array_equal(points._first_of_each(rec), ~(same & earlier).any(axis=1))


@pytest.mark.slow
@pytest.mark.parametrize("name, crs", [("delft", "EPSG:7415"), ("ign", None)])
def test_tile_sizes_and_workers_give_the_same_bytes(name, crs, request, tmp_path):
    """Issue 18: the same products, byte for byte, for three tile sizes and 1, 2 and 3
    workers (each run cuts the area into 8 to 75 tiles; the fixture run is one tile)."""
    from recon3d.config import PipelineConfig
    from recon3d.core.geo import parse_crs
    from recon3d.pipeline.run import run

    whole = request.getfixturevalue(f"{name}_run").out_dir
    path = shared(DELFT if name == "delft" else IGN)
    for size, workers in ((16, 1), (32, 2), (64, 3)):
        out = tmp_path / f"s{size}w{workers}"
        result = run(path, out, crs=parse_crs(crs) if crs else None, workers=workers, keep_points=False,
                     config=PipelineConfig().with_overrides([f"tiles.size={size}"]))
        assert result.auto["tiles"]["count"] > 1
        _same_products(out, whole, f"{size} m tiles, {workers} workers")


@pytest.mark.slow
def test_dask_local_cluster_gives_the_same_bytes(ign_run, tmp_path):
    """The tiles and the solids on a dask.distributed LocalCluster: the local run's bytes."""
    from recon3d.config import PipelineConfig
    from recon3d.pipeline.run import run

    out = tmp_path / "dask"
    result = run(shared(IGN), out, scheduler="local", config=PipelineConfig().with_overrides(["tiles.size=30"]))
    assert result.auto["executor"]["value"] == "dask local" and result.auto["tiles"]["count"] > 1
    _same_products(out, ign_run.out_dir, "dask")


def test_a_scheduler_that_does_not_answer(tmp_path):
    import time

    start = time.perf_counter()
    result = _cli("run", shared(IGN), "-o", tmp_path / "out", "--scheduler", "tcp://127.0.0.1:9", cwd=tmp_path)
    _refused(result, "--scheduler tcp://127.0.0.1:9", "no Dask scheduler answers")
    assert time.perf_counter() - start < 60
    assert list(tmp_path.iterdir()) == []


def test_a_tile_that_fails_is_tried_again_then_named(tmp_path, monkeypatch):
    """A tile failing once is done again; one failing twice stops the run with its name and
    reason, and nothing is published."""
    from recon3d.config import PipelineConfig
    from recon3d.pipeline import passes
    from recon3d.pipeline.executor import TileFailure
    from recon3d.pipeline.run import run

    real = passes.surface
    calls = {}

    def flaky(spec, tile, *args):
        calls[tile.name] = calls.get(tile.name, 0) + 1
        if tile.key == (0, 1) and (calls[tile.name] == 1 or always):
            raise OSError("disk went away")
        return real(spec, tile, *args)

    monkeypatch.setattr(passes, "surface", flaky)
    config = PipelineConfig().with_overrides(["tiles.size=32"])
    always = False
    run(shared(IGN), tmp_path / "once", config=config)
    assert calls["0_1"] == 2 and (tmp_path / "once" / "dsm.tif").exists()
    always = True
    calls.clear()
    with pytest.raises(TileFailure, match=r"1 of \d+ tiles failed twice in the surface pass: tile 0_1 .*disk went away"):
        run(shared(IGN), tmp_path / "twice", config=config)
    assert not (tmp_path / "twice").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["once"]


@pytest.mark.slow
def test_resume_after_a_kill_redoes_only_the_unfinished_tiles(delft_run, tmp_path):
    """kill -9 in the middle of a tiled run, then ``--resume``: the tiles done are taken
    up, the rest done, and the products are the bytes of an uninterrupted run; the work of
    another run (other settings) is refused."""
    import json
    import os
    import signal
    import time

    out = tmp_path / "out"
    args = [sys.executable, "-m", "recon3d", "-q", "run", str(shared(DELFT)), "--crs", "EPSG:7415", "-o", str(out),
            "--set", "tiles.size=16", "--workers", "1", "--resume"]
    proc = subprocess.Popen(args, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and len(list(tmp_path.glob(".out.partial-*/_work/tiles-*/*/ground.npz"))) < 20:
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = len(list(tmp_path.glob(".out.partial-*/_work/tiles-*/*/*.npz")))
    assert done >= 20 and not out.exists()
    other = subprocess.run([*args[:-1], "--set", "buildings.min_area=30", "--resume"], capture_output=True,
                           text=True, timeout=300)
    _refused(other, "different run", "config")
    result = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    notes = json.loads((out / "run.json").read_text())["notes"]
    assert any(f"took up the work of an earlier run ({done} tile results)" in n for n in notes), notes
    _same_products(out, delft_run.out_dir, "resumed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # the killed run's work folder is gone


def test_tile_mosaic_windows_match_the_whole_grid(tmp_path):
    """A window read from the tiles' saved results is the same cells as the whole placed
    grid's, on a finer grid too, across tile edges and past the grid's end."""
    from recon3d.pipeline.run import Grid
    from recon3d.pipeline.tiling import Tile

    shape, factor = (7, 11), 2
    tiles = [Tile((r, c), slice(r0, min(r0 + 4, 7)), slice(c0, min(c0 + 4, 11)))
             for r, r0 in enumerate(range(0, 7, 4)) for c, c0 in enumerate(range(0, 11, 4))]
    rng = np.random.default_rng(0)
    paths = []
    for t in tiles[:-1]:  # the last tile saved nothing: its cells keep the fill
        n, m = (t.rows.stop - t.rows.start) * factor, (t.cols.stop - t.cols.start) * factor
        paths.append(tmp_path / f"{t.name}.npz")
        np.savez(paths[-1], z=rng.normal(size=(n, m)))
    grid = Grid(None, shape, tiles[:-1], None, {}, [])
    whole = grid.place(paths, "z", factor=factor)
    assert np.isnan(whole[8:, 16:]).all() and np.isfinite(whole[:8]).all() and np.isfinite(whole[:, :16]).all()
    mosaic = grid.mosaic(paths, "z", factor=factor)
    assert mosaic.shape == whole.shape
    for window in [(slice(0, 14), slice(0, 22)), (slice(3, 11), slice(5, 17)), (slice(7, 9), slice(0, 30)),
                   (slice(12, 14), slice(20, 22))]:
        np.testing.assert_array_equal(mosaic[window], whole[window])


def test_a_buildings_points_are_gathered_from_its_tiles_in_one_order(tmp_path):
    from recon3d.pipeline.passes import gather_building_points

    rng = np.random.default_rng(3)
    xyz = rng.integers(0, 20, (500, 3)).astype(np.float64)  # many equal x: the survey order decides
    order = rng.permutation(10_000)[:500]
    part = rng.integers(0, 3, 500)
    paths = []
    for k in range(3):
        paths.append(tmp_path / f"t{k}.npz")
        np.savez(paths[-1], b7=xyz[part == k], o7=order[part == k], b8=xyz[:1], o8=order[:1])
    expected = xyz[np.lexsort((order, xyz[:, 0]))]
    np.testing.assert_array_equal(gather_building_points(paths, 7), expected)
    np.testing.assert_array_equal(gather_building_points(paths[::-1], 7), expected)
    assert gather_building_points([], 7).shape == (0, 3)


def test_footprint_depth_is_the_euclidean_distance_to_the_outline():
    from scipy import ndimage

    from recon3d.buildings.classes import footprint_depth

    rng = np.random.default_rng(4)
    labels = ndimage.label(ndimage.binary_opening(rng.random((90, 130)) > 0.2))[0]
    labels[:, :5] = 1  # a footprint running off the grid: its edge is an outline too
    expected = ndimage.distance_transform_edt(np.pad(labels > 0, 1))[1:-1, 1:-1] * 0.5
    depth = footprint_depth(labels, 0.5)
    assert depth.dtype == np.float32 and depth[:, 0].max() == 0.5
    np.testing.assert_allclose(depth, expected, rtol=1e-6)


def test_spilled_grids_keep_their_values_after_their_pages_are_released(tmp_path):
    from recon3d.pipeline.spill import Spill

    rng = np.random.default_rng(6)
    spill = Spill(tmp_path / "grids")
    grids = [rng.random((300, 200)).astype(np.float32), rng.random((70, 90)) > 0.5,
             rng.integers(0, 9, (40, 40)).astype(np.int32), np.zeros((0, 5), np.float32)]
    mapped = [spill(g) for g in grids]
    mapped[0][5, 7] = -1.0  # writable, and kept
    spill.release()
    grids[0][5, 7] = -1.0
    for g, m in zip(grids, mapped, strict=True):
        assert m.dtype == g.dtype and m.shape == g.shape
        np.testing.assert_array_equal(m, g)
    assert len(list((tmp_path / "grids").iterdir())) == 3  # nothing to map for an empty grid
