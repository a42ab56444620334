"""Readers and writers on real files: LAS/LAZ, GeoTIFF, vector footprints, check points."""

import numpy as np
import pyproj
import pytest
import shapely
import shapely.affinity
from affine import Affine

from conftest import AUTZEN, BDUNI, DELFT, IGN, shared
from recon3d.core.geo import crs_units, parse_crs
from recon3d.core.pointcloud import PointCloud
from recon3d.core.raster import Raster
from recon3d.errors import CRSError, InputError
from recon3d.io.checkpoints import read_checkpoints
from recon3d.io.geotiff import read_raster, write_raster
from recon3d.io.las import read_las, write_las
from recon3d.io.vectors import read_footprints, write_features


def test_las_without_crs_needs_one():
    with pytest.raises(CRSError, match="delft_ahn3_strip.laz: the file has no CRS"):
        read_las(shared(DELFT))
    cloud = read_las(shared(DELFT), crs=parse_crs("EPSG:7415"))
    assert len(cloud) == 208432
    assert set(np.unique(cloud.classification)) == {1, 2, 6, 9, 26}
    assert cloud.crs.to_epsg() == 7415


def test_las_crs_from_header_and_conflict():
    cloud = read_las(shared(IGN))
    assert cloud.crs.to_epsg() == 2154
    assert {"red", "green", "blue", "nir", "return_number", "number_of_returns"} <= set(cloud.attributes)
    with pytest.raises(CRSError, match="EPSG:2154 but --crs says EPSG:28992"):
        read_las(shared(IGN), crs=parse_crs("EPSG:28992"))


def test_feet_units_of_autzen():
    cloud = read_las(shared(AUTZEN))
    u = crs_units(cloud.crs)
    assert u.horizontal == pytest.approx(0.3048, rel=1e-5)
    assert u.vertical == u.horizontal
    assert u.length(2.5) == pytest.approx(8.2021, rel=1e-4)


def test_las_round_trip_keeps_classes_rgb_crs(tmp_path):
    cloud = read_las(shared(IGN))
    out = tmp_path / "c.laz"
    write_las(cloud, out)
    back = read_las(out)
    assert back.crs.equals(cloud.crs)
    np.testing.assert_allclose(back.xyz, cloud.xyz, atol=0.0006)
    for name in ("classification", "red", "nir", "return_number", "intensity"):
        np.testing.assert_array_equal(back.attributes[name], cloud.attributes[name])


def test_las_date_is_the_data_s_not_the_clock_s(tmp_path, monkeypatch):
    """The header's creation date is the one given (the survey's), else today, else the day
    of SOURCE_DATE_EPOCH: the same input gives the same bytes on any day."""
    import datetime as dt

    import laspy

    from recon3d.io.las import las_date

    cloud = PointCloud(np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]), {"classification": np.array([2, 6], np.uint8)})
    write_las(cloud, tmp_path / "given.laz", date="2014-03-04")
    assert las_date(tmp_path / "given.laz") == "2014-03-04"
    monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    write_las(cloud, tmp_path / "today.laz")
    assert laspy.open(tmp_path / "today.laz").header.creation_date == dt.datetime.now(dt.timezone.utc).date()
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    write_las(cloud, tmp_path / "a.laz")
    write_las(cloud, tmp_path / "b.laz")
    assert las_date(tmp_path / "a.laz") == "2023-11-14"
    assert (tmp_path / "a.laz").read_bytes() == (tmp_path / "b.laz").read_bytes()


def test_corrupt_truncated_and_empty_las(tmp_path):
    data = shared(IGN).read_bytes()
    bad = tmp_path / "truncated.laz"
    bad.write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError, match="truncated.laz: cannot read LAS/LAZ"):
        read_las(bad)
    garbage = tmp_path / "garbage.laz"
    garbage.write_bytes(b"this is not a point cloud" * 10)
    with pytest.raises(InputError, match="garbage.laz: cannot read"):
        read_las(garbage)
    empty = tmp_path / "empty.laz"
    write_las(PointCloud(np.zeros((1, 3)), {}, pyproj.CRS.from_epsg(2154)), empty)
    import laspy

    las = laspy.read(empty)
    las.points = las.points[:0]
    las.write(empty)
    with pytest.raises(InputError, match="empty.laz: the point cloud is empty"):
        read_las(empty)
    with pytest.raises(InputError, match="missing.laz: point cloud file not found"):
        read_las(tmp_path / "missing.laz")


def test_unknown_epsg():
    with pytest.raises(CRSError, match="unknown coordinate reference system 'EPSG:999999'"):
        parse_crs("EPSG:999999")


def test_geotiff_round_trip_nan_crs(tmp_path):
    data = np.arange(300 * 280, dtype=np.float32).reshape(300, 280)
    data[5:9, 7:11] = np.nan
    r = Raster(data, Affine(0.5, 0, 85000.0, 0, -0.5, 447600.0), parse_crs("EPSG:7415"), {"product": "DSM"})
    write_raster(r, tmp_path / "x.tif")
    back = read_raster(tmp_path / "x.tif")
    np.testing.assert_array_equal(np.isnan(back.data), np.isnan(data))
    np.testing.assert_array_equal(back.data[~np.isnan(data)], data[~np.isnan(data)])
    assert back.transform == r.transform and back.crs.to_epsg() == 7415
    import rasterio

    with rasterio.open(tmp_path / "x.tif") as src:
        assert src.dtypes[0] == "float32" and np.isnan(src.nodata)
        assert src.profile["tiled"] and src.compression.name == "deflate"


def test_footprints_read_and_reprojected(tmp_path):
    fps, notes = read_footprints(shared(BDUNI), crs=parse_crs("EPSG:2154"))
    assert len(fps) == 40 and all(f.polygon.is_valid and f.polygon.area > 5 for f in fps)
    # the same outlines written in WGS84 come back in Lambert-93 within a millimetre
    wgs = tmp_path / "wgs84.geojson"
    t = pyproj.Transformer.from_crs(2154, 4326, always_xy=True)
    geoms = [shapely.transform(f.polygon, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1]))) for f in fps]
    write_features(wgs, geoms, [{"id": f.id} for f in fps], pyproj.CRS.from_epsg(4326))
    back, _ = read_footprints(wgs, crs=parse_crs("EPSG:2154"))
    assert len(back) == 40
    assert max(a.polygon.symmetric_difference(b.polygon).area for a, b in zip(fps, back, strict=True)) < 1e-3


def test_invalid_and_multi_polygons_are_repaired(tmp_path):
    bowtie = shapely.Polygon([(0, 0), (10, 10), (10, 0), (0, 10)])
    multi = shapely.MultiPolygon([shapely.box(20, 0, 30, 10), shapely.box(40, 0, 50, 10)])
    line_like = shapely.Polygon([(0, 0), (1, 0), (2, 0)])
    # in France, where Lambert 93 is used (the CRS's area of use is checked)
    bowtie, multi, line_like = (shapely.affinity.translate(g, 870000, 6617000) for g in (bowtie, multi, line_like))
    f = tmp_path / "bad.geojson"
    write_features(f, [bowtie, multi, line_like], [{"id": "a"}, {"id": "b"}, {"id": "c"}], pyproj.CRS.from_epsg(2154))
    fps, notes = read_footprints(f, crs=parse_crs("EPSG:2154"))
    assert [fp.id for fp in fps] == ["a-1", "a-2", "b-1", "b-2"]
    assert all(fp.polygon.is_valid for fp in fps)
    assert any("a: invalid polygon repaired" in n for n in notes)
    assert any("c:" in n and "skipped" in n for n in notes)


def test_checkpoints(tmp_path):
    f = tmp_path / "cp.csv"
    f.write_text("x,y,z,id,kind\n1,2,3,p1,ground\n4,5,6,p2,roof\n7,8,9,,\n")
    cp = read_checkpoints(f)
    assert cp.xyz.shape == (3, 3) and list(cp.kinds) == ["ground", "roof", ""] and cp.ids[2] == "3"
    f.write_text("x,y,z\n1,2,nan\n")
    with pytest.raises(InputError, match="line 2: x, y and z must be finite"):
        read_checkpoints(f)
    f.write_text("x,y\n1,2\n")
    with pytest.raises(InputError, match="header must contain x,y,z"):
        read_checkpoints(f)
