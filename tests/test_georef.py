"""Every product names its CRS: an EPSG code found for an ESRI WKT such as Autzen's, or
the WKT where no code exists."""

import json
import re
import sqlite3
import struct

import laspy
import numpy as np
import pyogrio
import pyproj
import pytest
import rasterio
from conftest import AUTZEN, shared
from rasterio.crs import CRS as GdalCRS

from recon3d.core.geo import crs_name, identify_crs

RASTERS = ("dsm", "dtm", "ndsm", "model_dsm")

#: Oregon Lambert as EPSG:2994 but with another standard parallel: no EPSG CRS is it.
CUSTOM_LCC = ("+proj=lcc +lat_1=43.2 +lat_2=45.5 +lat_0=41.75 +lon_0=-120.5 +x_0=400000 +y_0=0 "
              "+ellps=GRS80 +units=ft +no_defs")


def _glb_extras(path):
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])["scenes"][0]["extras"]["recon3d"]


def _las_wkt(path):
    header = laspy.read(path).header
    assert header.global_encoding.wkt
    return next(v.string for v in header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr))


# ------------------------------------------------------------------ identification


def test_autzen_esri_wkt_is_epsg_2994():
    with laspy.open(shared(AUTZEN)) as reader:
        given = reader.header.parse_crs()
    assert given.to_epsg() is None  # PROJ alone finds nothing: the datum is named the ESRI way
    found = identify_crs(given)
    assert found.code == "EPSG:2994" and found.confidence >= 70 and "ESRI" in found.how
    assert found.crs.equals(given, ignore_axis_order=True) and found.crs.to_epsg() == 2994
    assert found.warnings() == [] and found.record()["given"] == "NAD_1983_HARN_Lambert_Conformal_Conic"


def test_identified_codes_and_compounds():
    assert identify_crs(pyproj.CRS("EPSG:7415")).code == "EPSG:7415"
    assert identify_crs(pyproj.CRS("EPSG:7415")).confidence == 100
    # a compound CRS without a code of its own: identified part by part, CityJSON told
    pair = identify_crs(pyproj.CRS("EPSG:2994+6360"))
    assert pair.code == "EPSG:2994+6360" and crs_name(pair.crs) == "EPSG:2994+6360"
    assert "horizontal EPSG:2994 only" in pair.warnings()[0]
    # the WKT of RD New + NAP stripped of every authority is still EPSG:7415
    bare = re.sub(r',AUTHORITY\["EPSG","\d+"\]', "", pyproj.CRS("EPSG:7415").to_wkt("WKT1_GDAL"))
    assert identify_crs(pyproj.CRS.from_wkt(bare)).code == "EPSG:7415"
    # a WKT1 with TOWGS84 (a bound CRS, as older LAS writers put it) is the CRS it binds
    towgs84 = pyproj.CRS(2154).to_wkt("WKT1_GDAL").replace('AUTHORITY["EPSG","7019"]]', 'AUTHORITY["EPSG","7019"]],TOWGS84[0,0,0,0,0,0,0]')
    bound = identify_crs(pyproj.CRS.from_wkt(towgs84))
    assert pyproj.CRS.from_wkt(towgs84).is_bound and bound.code == "EPSG:2154" and "TOWGS84" in bound.how


def test_crs_without_code_is_said_so():
    found = identify_crs(pyproj.CRS.from_proj4(CUSTOM_LCC))
    assert found.code is None and found.record()["written_as"] == "WKT only"
    assert found.best_guess and "%" in found.best_guess  # a near miss, below the confidence taken
    assert "no EPSG code" in found.warnings()[0]


def test_cityjson_url_of_a_compound_without_code():
    from recon3d.io.cityjson import crs_url

    assert crs_url(pyproj.CRS("EPSG:2994+6360")) == "https://www.opengis.net/def/crs/EPSG/0/2994"
    assert crs_url(pyproj.CRS("EPSG:7415")) == "https://www.opengis.net/def/crs/EPSG/0/7415"


# ------------------------------------------------------------------ every output of a run


def test_autzen_every_output_carries_epsg_2994(autzen_run):
    out = autzen_run.out_dir
    for name in RASTERS:
        with rasterio.open(out / f"{name}.tif") as src:
            assert src.crs.to_epsg() == 2994, name
    wkt = _las_wkt(out / "cloud.laz")
    assert wkt.startswith("PROJCS[") and 'AUTHORITY["EPSG","2994"]' in wkt  # WKT1, as PDAL writes
    assert laspy.read(out / "cloud.laz").header.parse_crs().to_epsg() == 2994
    assert GdalCRS.from_wkt(wkt).to_epsg() == 2994  # GDAL, which PDAL reads it with
    city = json.loads((out / "buildings.city.json").read_text())
    assert city["metadata"]["referenceSystem"] == "https://www.opengis.net/def/crs/EPSG/0/2994"
    assert _glb_extras(out / "buildings.glb")["crs"] == "EPSG:2994"
    assert "# CRS: EPSG:2994\n" in (out / "buildings.obj").read_text()
    assert pyogrio.read_info(out / "footprints.gpkg")["crs"] == "EPSG:2994"
    with sqlite3.connect(out / "footprints.gpkg") as db:
        assert db.execute("select organization, organization_coordsys_id from gpkg_spatial_ref_sys "
                          "join gpkg_contents using (srs_id)").fetchall() == [("EPSG", 2994)]
    geojson = json.loads((out / "footprints.geojson").read_text())
    assert geojson["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::2994"
    run = json.loads((out / "run.json").read_text())
    assert run["inputs"]["crs"] == "EPSG:2994"
    ident = run["inputs"]["crs_identification"]
    assert ident["epsg"] == "EPSG:2994" and ident["confidence"] >= 70 and ident["given"].startswith("NAD_1983_HARN")


def test_footprints_gpkg_matches_geojson(autzen_run):
    out = autzen_run.out_dir
    a, b = (pyogrio.read_info(out / f"footprints.{s}") for s in ("gpkg", "geojson"))
    assert a["features"] == b["features"] == len(autzen_run.city)
    assert list(a["fields"]) == list(b["fields"])
    np.testing.assert_allclose(a["total_bounds"], b["total_bounds"], atol=1e-6)


@pytest.fixture(scope="module")
def custom_run(tmp_path_factory):
    """Autzen relabelled in a Lambert CRS no EPSG code describes (another standard parallel)."""
    from recon3d.io.las import read_las, write_las
    from recon3d.pipeline.run import run

    folder = tmp_path_factory.mktemp("custom")
    cloud = read_las(shared(AUTZEN))
    cloud.crs = pyproj.CRS.from_proj4(CUSTOM_LCC)
    write_las(cloud, folder / "custom.laz")
    return run(folder / "custom.laz", folder / "out")


def test_crs_without_code_travels_as_wkt(custom_run):
    out, crs = custom_run.out_dir, custom_run.cloud.crs
    run = json.loads((out / "run.json").read_text())
    assert run["inputs"]["crs_identification"]["epsg"] is None
    assert any("no EPSG code" in w for w in run["warnings"])
    for name in RASTERS:
        with rasterio.open(out / f"{name}.tif") as src:
            assert pyproj.CRS.from_wkt(src.crs.to_wkt()).equals(crs, ignore_axis_order=True), name
    assert laspy.read(out / "cloud.laz").header.parse_crs().equals(crs, ignore_axis_order=True)
    assert pyproj.CRS.from_user_input(pyogrio.read_info(out / "footprints.gpkg")["crs"]).equals(crs)
    assert pyproj.CRS.from_wkt(_glb_extras(out / "buildings.glb")["crs_wkt"]).equals(crs)
    line = next(t for t in (out / "buildings.obj").read_text().splitlines() if t.startswith("# CRS WKT: "))
    assert pyproj.CRS.from_wkt(line.removeprefix("# CRS WKT: ")).equals(crs)
    assert "referenceSystem" not in json.loads((out / "buildings.city.json").read_text())["metadata"]
