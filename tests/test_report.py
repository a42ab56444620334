"""report.html: self-contained, every section filled, numbers rounded for people."""

import json
import re
from html.parser import HTMLParser

import numpy as np
from click.testing import CliRunner

from recon3d.cli import cli
from recon3d.report import html as report_html


class _Tables(HTMLParser):
    """Each table's class and its rows of cell texts; the page's visible text."""

    def __init__(self):
        super().__init__()
        self.tables, self.text, self._cell, self._skip = [], [], None, 0

    def handle_starttag(self, tag, attrs):
        if tag in ("script", "style", "svg"):
            self._skip += 1
        elif tag == "table":
            self.tables.append((dict(attrs).get("class") or "", []))
        elif tag == "tr" and self.tables:
            self.tables[-1][1].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("script", "style", "svg"):
            self._skip -= 1
        elif tag in ("td", "th") and self._cell is not None:
            self.tables[-1][1][-1].append("".join(self._cell).strip())
            self._cell = None

    def handle_data(self, data):
        if self._skip:
            return
        self.text.append(data)
        if self._cell is not None:
            self._cell.append(data)

    def table(self, cls: str) -> list[list[str]]:
        """The body rows of the first table whose class holds ``cls`` (header row dropped)."""
        return next(rows[1:] for c, rows in self.tables if cls in c.split())


def _parse(out_dir) -> _Tables:
    parser = _Tables()
    parser.feed((out_dir / "report.html").read_text(encoding="utf-8"))
    return parser


def _json(out_dir, name):
    return json.loads((out_dir / name).read_text(encoding="utf-8"))


def test_report_is_self_contained_and_filled(delft_run):
    page = (delft_run.out_dir / "report.html").read_text(encoding="utf-8")
    assert "http://" not in page.replace('xmlns="http://www.w3.org/2000/svg"', "") and "https://" not in page
    for section in ("Warnings and notes", "Accuracy", "Ground filter", "Building detection", "Surfaces", "Buildings",
                    "Timings", "Parameters"):
        assert f"<h2>{section}</h2>" in page
    assert len(re.findall(r"data:image/png;base64,", page)) == 4  # DSM, DTM, nDSM, buildings map
    for needle in ("scalebar", "class=north", "northing (EPSG:7415", "easting (EPSG:7415", "no data"):
        assert needle in page, needle
    assert page.count('aria-label="error histogram"') >= 2
    assert page.count('<path data-b="') == len(delft_run.city)
    assert "provider ground points" in page
    assert "<h2>Stereo</h2>" not in page  # LiDAR: no stereo section


def test_report_numbers_are_the_json_values_rounded(delft_run):
    out = delft_run.out_dir
    report, run, parsed = _json(out, "report.json"), _json(out, "run.json"), _parse(out)
    rows = parsed.table("accuracy")
    assert len(rows) == len(report["accuracy"])
    for cells, r in zip(rows, report["accuracy"], strict=True):
        assert cells[:3] == [r["product"], r["reference"], f"{r['n']:,}"]
        assert cells[3:8] == [f"{r[k]:.2f}" for k in ("mean", "std", "rms", "max_abs", "nmad")]  # to the cm
        assert cells[8:10] == [f"{r[k]:.1f}" for k in ("within_1m", "within_2m")]  # % to 0.1
    g = dict(parsed.table("kv"))  # the ground filter's table comes first
    assert g["Type I % (ground rejected)"] == f"{report['ground_filter']['type_i_percent']:.1f}"
    assert g["Cohen's kappa"] == f"{report['ground_filter']['kappa']:.3f}"
    detection = parsed.table("detection")
    a = report["buildings_vs_provider_area"]
    assert detection[0][1:] == [f"{a[k]:.1f}" for k in ("completeness", "correctness", "quality")]
    # one row per building, its figures rounded
    features = _json(out, "footprints.geojson")["features"]
    table = parsed.table("buildings")
    assert [r[0] for r in table] == [f["properties"]["id"] for f in features]
    for cells, f in zip(table, features, strict=True):
        p = f["properties"]
        assert cells[7] == (f"{p['height_m']:.2f}" if p["height_m"] is not None else "n/a")
        assert cells[9] == (f"{p['roof_rms_m']:.2f}" if p.get("roof_rms_m") is not None else "n/a")
        assert cells[10] == p["status"] and cells[11] == (p["reason"] or "–")
        if p.get("roof_points_off_1m_share") is not None:  # per-building fit quality, % to 0.1
            assert cells[12] == f"{p['roof_points_per_m2']:.1f}"
            assert cells[13] == f"{100 * p['roof_points_off_1m_share']:.1f}"
            n, area = p["roof_unmodelled_parts"], p["roof_unmodelled_area_m2"]
            assert cells[14] == (f"{n} · {area:,.1f}" if n else "0")
            assert cells[15] == f"{100 * p['footprint_empty_share']:.1f}"
    assert sum(r[10] == "fallback" for r in table) == report["buildings"]["statuses"].get("fallback", 0)
    # nothing with the digits of a float dump, no stage that did not run
    text = " ".join(parsed.text)
    assert not re.search(r"\d\.\d{4,}", text), re.search(r".{40}\d\.\d{4,}.{20}", text)
    timings = next(rows for c, rows in parsed.tables if rows and rows[0][:2] == ["stage", "seconds"])
    assert "stereo" not in [r[0] for r in timings] and "change" not in [r[0] for r in timings]
    assert timings[-1][1] == f"{sum(v for k, v in run['timings_s'].items() if k not in ('stereo', 'change')):.2f}"


def test_report_defines_one_building_count(delft_run):
    """10 buildings in the CLI and the report; the CityJSON's Buildings and BuildingParts both named."""
    out = delft_run.out_dir
    objects = _json(out, "buildings.city.json")["CityObjects"].values()
    n_building = sum(o["type"] == "Building" for o in objects)
    n_part = sum(o["type"] == "BuildingPart" for o in objects)
    assert n_part > 0  # Delft holds a block (the test means something)
    text = "".join(_parse(out).text)
    assert f"{len(delft_run.city)} buildings, one per footprint" in text
    assert f"they are {n_building} Building objects and {n_part} BuildingPart objects" in text
    part_rows = [r for r in _parse(out).table("buildings") if r[1].startswith("BuildingPart of ")]
    assert len(part_rows) == n_part


def test_ground_filter_without_objects_is_not_applicable():
    """A provider classifying ground only (Autzen: classes 1 and 2): kappa 0 means nothing, it reads n/a."""
    from recon3d.quality.evaluate import ground_filter_errors

    classes = np.array([2] * 99 + [1] * 300 + [2])
    errors = ground_filter_errors(np.arange(400) != 0, classes)  # one ground point rejected
    assert errors["reference_objects"] == 0 and errors["kappa"] == 0.0
    section = report_html._ground_section(errors)
    assert section.count("<td>n/a</td>") == 2 and "0.000" not in section and "do not apply" in section
    assert "<td>1.0</td>" in section and "<td>25.0</td>" in section  # Type I %, share scored %
    with_objects = ground_filter_errors(np.arange(400) < 100, np.array([2] * 100 + [6] * 300))
    assert "<td>1.000</td>" in report_html._ground_section(with_objects)


def test_stereo_sections_round_their_figures():
    frame = {"candidates": [{"pair": "a-b", "base_to_height": 0.398, "overlap": 1.0, "common_points": 400, "used": True}],
             "pairs": [{"pair": "a-b", "vertical_parallax_px": {"median": 0.2134, "p90": 0.644}, "matched_percent": 81.654,
                        "matching": {"engine": "census", "disparity_range_searched": {"value": [-26, 57]}},
                        "self_check": {"coverage_percent": 98.75, "discrepancy_m": 0.0195, "discrepancy_p90_m": 0.1104,
                                       "discrepancy_gsd": 0.074, "reprojection_px": 0.0039},
                        "fused_share_percent": 100.0}],
             "pair_count": 1, "ground_sample_distance": 0.2527, "points": 702376,
             "common_area": {"area_m2": 43139.2, "filled_percent": 100.0, "observed_percent": 92.45}}
    html = report_html._stereo_section(frame)
    for shown in (">0.40<", ">81.7<", ">0.21<", ">98.8<", ">0.02<", ">702,376<", ">92.5<", "-26 … 57"):
        assert shown in html, shown
    tile = {"tile": 0, "core": [0, 0, 800, 801], "bias_px": [0.507, -0.009], "search_heights_m": [46.63, 200.29],
            "search_from": "1475 tie points in the tile", "vertical_parallax_px": {"median": 0.119},
            "matched_percent": 95.09, "points": 614950}
    satellite = {"tiles": {"per_tile": [tile], "failures": [{"tile": 1, "core": [800, 0, 1600, 801],
                                                             "reason": "no tie point in the tile"}]},
                 "tie_points": {"sift_matches": 1509, "on_epipolar_curves": 1475, "epipolar_tolerance_px": 1.0},
                 "tie_heights_m": [12.71, 214.7], "vertical_parallax_px": {"median": 0.119, "p90": 0.411},
                 "matched_percent": 95.09, "self_check": {"tie_points": 1473, "median_px": 0.131, "median_m": 0.752,
                                                          "within_1px_percent": 99.32}}
    html = report_html._satellite_section(satellite)
    for shown in ("0.51, -0.01", "46.6 … 200.3", ">95.1<", "failed: no tie point in the tile", "1 / 1",
                  "0.13 / 0.75", ">99.3<", "12.7 … 214.7"):
        assert shown in html, shown


def test_textured_model_paragraph():
    textures = {"roof_triangles_textured": 1233, "wall_surfaces": 735, "wall_surfaces_textured": 583,
                "wall_surfaces_from_ortho": 282, "textures": [{"name": "ortho", "size": [968, 764], "reduced": 1},
                                                              {"name": "left.png", "size": [3000, 4096], "reduced": 3}]}
    html = report_html._textures_html(textures)
    for shown in ("301 of 735 walls", "282 low steps", "ortho (968 x 764 px)", "left.png (3000 x 4096 px, reduced 3 x)"):
        assert shown in html, shown
    assert report_html._textures_html(None) == ""


def test_report_command_regenerates(delft_run, tmp_path):
    before = (delft_run.out_dir / "report.html").read_bytes()
    result = CliRunner().invoke(cli, ["report", str(delft_run.out_dir)])
    assert result.exit_code == 0 and "report.html" in result.output
    assert (delft_run.out_dir / "report.html").read_bytes() == before  # same run, same bytes
    bad = CliRunner().invoke(cli, ["report", str(tmp_path)])
    assert bad.exit_code == 1 and "not a recon3d output folder" in bad.output


def test_scale_bar_is_in_metres_whatever_the_crs_unit():
    """A map 2000 ft wide (609.6 m): the bar's drawn length is its label in metres at the map's scale."""
    from recon3d.report import maps

    frame = maps.MapFrame.fit((0.0, 0.0, 2000.0, 1000.0))
    bar = maps._scale_bar(frame, metres_per_unit=0.3048)
    label = float(re.search(r">(\d+) m</text>", bar).group(1))
    drawn = sum(float(w) for w in re.findall(r'<rect x="[\d.]+" y="[\d.]+" width="([\d.]+)" height="6"', bar))
    assert abs(drawn - label / 0.3048 * frame.scale) < 0.5
    assert 0.15 < drawn / frame.width < 0.4 and label == 200.0  # about a quarter: 1, 2 or 5 x 10^k m


def test_no_data_is_transparent():
    from recon3d.report import maps

    z = np.add.outer(np.arange(40.0), np.arange(60.0)) * 0.1
    z[5:15, 10:30] = np.nan
    rgba = maps.shaded_relief(z, 0.5, 0.0, 10.0, "terrain", factor=2)
    assert rgba.shape == (80, 120, 4)
    assert (rgba[10:30, 20:60, 3] == 0).all() and (rgba[40:, :, 3] == 255).all()
    assert np.ptp(rgba[40:, :, :3].astype(int)) > 50  # tinted by height, not flat


def test_large_rasters_are_embedded_near_display_size():
    from recon3d.report import maps

    frame = maps.MapFrame.fit((0.0, 0.0, 3000.0, 2000.0))
    factor = maps.resample_factor((4000, 6000), frame)
    rgba = maps.shaded_relief(np.random.default_rng(0).normal(size=(400, 600)), 1.0, -1, 1, "terrain", factor)
    assert factor * 6000 == 2 * frame.width and rgba.shape[1] == round(600 * factor)
    assert maps.resample_factor((100, 200), frame) == 2.0  # small: up, by a whole factor
