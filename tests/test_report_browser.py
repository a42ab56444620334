"""report.html in headless Chromium: it renders, offline, with every element in place."""

import json
import shutil

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from conftest import chromium

from recon3d.cli import cli

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    path = chromium()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=path, args=["--no-sandbox", "--disable-gpu"])
        yield b
        b.close()


def _open(browser, out_dir, png):
    """The rendered report page, its full-page screenshot written to ``png``, and the
    URLs it asked for beyond its own file and data URIs."""
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    requests = []
    page.on("request", lambda r: requests.append(r.url) if not r.url.startswith(("file:", "data:")) else None)
    page.goto((out_dir / "report.html").resolve().as_uri(), wait_until="load")
    page.screenshot(path=str(png), full_page=True)
    return page, requests


def _check_page(page, requests, png, out_dir):
    run = json.loads((out_dir / "run.json").read_text(encoding="utf-8"))
    features = json.loads((out_dir / "footprints.geojson").read_text(encoding="utf-8"))["features"]
    assert requests == []  # self-contained: no network
    # not blank: a tall page with pictures, not a white sheet
    shot = cv2.imread(str(png))
    assert shot.shape[0] > 3000
    assert (shot.min(axis=2) < 200).mean() > 0.04 and shot.std() > 30  # measured 0.08 and 42 on Delft
    # every image decoded (DSM, DTM, nDSM, buildings map)
    sizes = page.evaluate("Array.from(document.images).map(i => [i.complete, i.naturalWidth, i.naturalHeight])")
    assert len(sizes) == 4 and all(c and w > 100 and h > 100 for c, w, h in sizes), sizes
    # one table row and one map shape per building, the footprint's rings as sub-paths (courtyards as holes)
    ids = page.eval_on_selector_all("table.buildings tbody tr", "rows => rows.map(r => r.cells[0].textContent)")
    assert ids == [f["properties"]["id"] for f in features]
    rings = page.eval_on_selector_all("g.bldg path", "ps => ps.map(p => (p.getAttribute('d').match(/M/g) || []).length)")
    assert rings == [sum(len(p) for p in _polygons(f["geometry"])) for f in features]
    # every warning and note of run.json listed at the top
    listed = page.eval_on_selector_all("#warnings li", "items => items.map(i => i.textContent)")
    assert listed == [f"warning{w}" for w in run["warnings"]] + [f"note{n}" for n in run["notes"]]
    if not listed:
        assert page.is_visible("#no-warnings")
    for needle in (".scalebar", ".north", "#building-count"):
        assert page.locator(needle).count() >= 1, needle


def _polygons(geometry):
    return geometry["coordinates"] if geometry["type"] == "MultiPolygon" else [geometry["coordinates"]]


def test_report_renders_in_chromium(browser, delft_run, tmp_path):
    page, requests = _open(browser, delft_run.out_dir, tmp_path / "delft.png")
    _check_page(page, requests, tmp_path / "delft.png", delft_run.out_dir)
    # sorting by height puts the lowest building first, then the highest
    heights = page.eval_on_selector_all("table.buildings tbody tr", "rows => rows.map(r => r.cells[7].dataset.v)")
    page.click("table.buildings th:nth-child(8)")
    first = page.eval_on_selector("table.buildings tbody tr", "r => r.cells[7].dataset.v")
    assert float(first) == min(float(h) for h in heights if h)
    page.click("table.buildings th:nth-child(8)")
    first = page.eval_on_selector("table.buildings tbody tr", "r => r.cells[7].dataset.v")
    assert float(first) == max(float(h) for h in heights if h)


def test_report_lists_every_warning_and_note(browser, ign_run, tmp_path):
    """A run's warnings and notes (here added to a copy's run.json) are listed, in order, at the top."""
    out = tmp_path / "out"
    shutil.copytree(ign_run.out_dir, out)
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    run["warnings"] += ["tile 3 failed: no tie point in the tile", "1 footprint with no data under it: bd42"]
    run["notes"] += ["2 footprints got no solid: bd7, bd9"]
    (out / "run.json").write_text(json.dumps(run), encoding="utf-8")
    assert CliRunner().invoke(cli, ["report", str(out)]).exit_code == 0
    page, requests = _open(browser, out, tmp_path / "ign.png")
    _check_page(page, requests, tmp_path / "ign.png", out)
    # the warnings come first on the page
    top = page.evaluate("document.querySelector('#warnings').getBoundingClientRect().top")
    assert top < page.evaluate("document.querySelector('#accuracy').getBoundingClientRect().top")
    assert np.isfinite(top)
