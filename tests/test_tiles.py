"""A survey delivered as LAS/LAZ tiles: files, a folder or a glob read as one cloud, the
same products byte for byte as the whole file, and the bad tile sets refused."""

import hashlib
import subprocess
import sys

import laspy
import numpy as np
import pytest
from conftest import IGN, shared

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
