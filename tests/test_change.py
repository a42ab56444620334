"""Change detection against an older building database (recon3d.quality.change)."""

from __future__ import annotations

import numpy as np
import pyproj
import pytest
import shapely
from affine import Affine
from scipy import ndimage
from shapely import affinity

from recon3d.core.city import Building, CityModel
from recon3d.core.raster import Raster
from recon3d.errors import InputError
from recon3d.io.vectors import Footprint, read_footprints, write_features
from recon3d.quality.change import (
    CHANGE_CODES,
    ChangeParams,
    change_features,
    change_raster,
    detect_changes,
    match_groups,
    point_density,
    updated_model,
)
from conftest import BDUNI, shared

CRS = pyproj.CRS.from_epsg(2154)
X0, Y0 = 870000.0, 6617000.0  # national-grid sized coordinates


def box(x, y, w, h):
    return shapely.box(X0 + x, Y0 + y, X0 + x + w, Y0 + y + h)


# --------------------------------------------------------------------------- synthetic


def _synthetic():
    """Hand-made old database, new model and nDSM (0.5 m cells, 120 m x 100 m)."""
    res = 0.5
    transform = Affine(res, 0, X0, 0, -res, Y0 + 100)
    ndsm = np.zeros((200, 240), np.float32)
    ndsm[:40, 200:] = np.nan  # a no-data hole at x 100..120, y 80..100
    grid = Raster(ndsm, transform, CRS)
    new = []

    def add_new(bid, poly, h, roof_type=None):
        x, y = grid.cell_centers()
        inside = shapely.contains_xy(poly, x[None, :], y[:, None])
        grid.data[inside & np.isfinite(grid.data)] = h
        attrs = {"roof_type": roof_type} if roof_type else {}
        new.append(Building(bid, poly, 100.0, 100.0 + h, status="ok", attributes=attrs))

    old = []

    def add_old(fid, poly, **attrs):
        old.append(Footprint(fid, poly, attrs))

    # A: unchanged, mapped 1 m off
    add_old("A", box(5, 5, 10, 10), roof_z=108.0)
    add_new("a", box(6, 5, 10, 10), 8.0)
    # B: one old block, two new halves (split): unchanged 1:n
    add_old("B", box(25, 5, 20, 10), roof_z=107.0)
    add_new("b1", box(25, 5, 10, 10), 7.0)
    add_new("b2", box(35, 5, 10, 10), 7.0)
    # C: two old row houses, one new block (merge): unchanged n:1
    add_old("C1", box(55, 5, 8, 10), roof_z=106.0)
    add_old("C2", box(63, 5, 8, 10), roof_z=106.0)
    add_new("c", box(55, 5, 16, 10), 6.0)
    # D: old only, flat open ground in the data: demolished
    add_old("D", box(5, 30, 10, 10), roof_z=106.0)
    # E: new only: new
    add_new("e", box(25, 30, 10, 12), 6.0)
    # F: extension by half
    add_old("F", box(45, 30, 10, 10), roof_z=107.0)
    add_new("f", box(45, 30, 15, 10), 7.0)
    # G: raised by 5 m
    add_old("G", box(70, 30, 10, 10), roof_z=105.0)
    add_new("g", box(70, 30, 10, 10), 10.0)
    # H: roof type changed
    add_old("H", box(5, 55, 10, 10), roof_z=107.0, roof_type="flat")
    add_new("h", box(5, 55, 10, 10), 7.0, "gable")
    # I: outside the grid, J: in the no-data hole: not observed (no data is not no building)
    add_old("I", box(300, 300, 10, 10), roof_z=107.0)
    add_old("J", box(105, 85, 10, 10), roof_z=107.0)
    # K: a self-intersecting (bow-tie) old polygon over A2, repaired
    corners = [(30, 55), (40, 65), (40, 55), (30, 65)]
    bow = shapely.Polygon([(X0 + x, Y0 + y) for x, y in corners])
    add_old("K", bow, roof_z=107.0)
    add_new("k", box(30, 55, 10, 10), 7.0)
    city = CityModel(new, CRS)
    return old, city, grid


EXPECTED = {
    ("A",): "unchanged",
    ("B",): "unchanged",
    ("C1", "C2"): "unchanged",
    ("D",): "demolished",
    (): "new",
    ("F",): "footprint_changed",
    ("G",): "height_changed",
    ("H",): "roof_changed",
    ("I",): "not_observed",
    ("J",): "not_observed",
    ("K",): "footprint_changed",  # the repaired bow-tie is two triangles, half the new square
}


def test_synthetic_classes_exact():
    old, city, ndsm = _synthetic()
    result = detect_changes(old, city, ndsm)
    got = {tuple(r["old_ids"]): r for r in result.changes}
    assert {k: r["class"] for k, r in got.items()} == EXPECTED
    assert got[("B",)]["match"] == "1:m" and got[("C1", "C2")]["match"] == "n:1"
    assert got[("F",)]["subtype"] == "extension"
    assert got[("F",)]["old_area"] == 100 and got[("F",)]["new_area"] == 150
    assert got[("G",)]["dh"] == pytest.approx(5.0)
    assert got[("A",)]["iou"] < 0.9 and got[("A",)]["shape_share"] == 0  # 1 m shift tolerated
    assert got[("D",)]["confidence"] > 0.9 and got[("J",)]["coverage"] == 0
    assert all(0 <= r["confidence"] <= 1 for r in result.changes)
    assert result.summary["unchanged"] == 3 and result.summary["not_observed"] == 2
    assert any("repaired" in n for n in result.notes)
    # a 6 m height threshold hides G's 5 m raise
    lenient = detect_changes(old, city, ndsm, config=ChangeParams(height_threshold=6.0))
    assert {tuple(r["old_ids"]): r["class"] for r in lenient.changes}[("G",)] == "unchanged"


def test_synthetic_outputs(tmp_path):
    old, city, ndsm = _synthetic()
    result = detect_changes(old, city, ndsm)
    geoms, props = change_features(result)
    assert len(geoms) == len(props) == len(result.changes)
    write_features(tmp_path / "changes.geojson", geoms, props, CRS)
    back, _ = read_footprints(tmp_path / "changes.geojson", crs=CRS)
    assert len(back) >= len(geoms)
    assert len(change_features(result, changed_only=True)[0]) == len(result.changes) - 5

    layer = change_raster(result, ndsm)
    assert layer.data.dtype == np.float32 and layer.transform == ndsm.transform
    x, y = X0 + 50, Y0 + 35  # inside F
    code = layer.sample(np.array([x]), np.array([y]), bilinear=False)[0]
    assert code == CHANGE_CODES["footprint_changed"]
    assert np.isnan(layer.data[-1, -1])

    model = updated_model(old, city, result)
    ids = {b.id: b for b in model.buildings}
    assert "D" not in ids  # demolished
    assert ids["A"].footprint.equals(box(6, 5, 10, 10))  # unchanged keeps its old id, new geometry
    assert ids["G"].attributes["change"] == "height_changed"
    assert ids["b1"].attributes["lineage_old_ids"] == "B"
    assert ids["c"].attributes["lineage_old_ids"] == "C1,C2"
    assert ids["e"].attributes["change"] == "new"
    assert ids["I"].status == "failed" and ids["I"].reason == "not_observed"


def test_groups_split_merge():
    old = np.array([box(0, 0, 10, 10), box(10, 0, 10, 10), box(50, 0, 10, 10)], dtype=object)
    new = [box(0.5, 0, 19, 10), box(50, 0, 5, 10), box(55, 0, 5, 10), box(90, 0, 5, 5)]
    new = np.array(new, dtype=object)
    groups = sorted(match_groups(old, new, 0.1))
    assert groups == [([], [3]), ([0, 1], [0]), ([2], [1, 2])]


def test_bad_inputs():
    old, city, ndsm = _synthetic()
    no_heights = [Footprint(o.id, o.polygon, {}) for o in old]
    result = detect_changes(no_heights, city, ndsm)
    assert any("no height attribute" in n for n in result.warnings)
    assert result.summary["height_changed"] == 0
    far = [Footprint("x", box(10_000, 10_000, 10, 10), {})]
    with pytest.raises(InputError, match="does not overlap"):
        detect_changes(far, city, ndsm)
    with pytest.raises(InputError):
        detect_changes([Footprint("e", shapely.Polygon(), {})], city, ndsm)
    overlapping = [*old, Footprint("A", box(5, 5, 10, 10), {})]  # repeated id, same outline
    result = detect_changes(overlapping, city, ndsm)
    assert any("overlap" in n for n in result.notes) and any("repeated" in n for n in result.notes)


# --------------------------------------------------------------------------- real data


def _open_ground(ndsm: Raster, avoid, size_m: float = 8.0):
    """A size_m square on flat open ground with data, away from every building."""
    n = int(size_m / ndsm.resolution)
    ok = np.isfinite(ndsm.data) & (ndsm.data < 0.3)
    x, y = ndsm.cell_centers()
    near = shapely.intersects_xy(shapely.union_all(avoid).buffer(4.0), x[None, :], y[:, None])
    ok &= ~near
    free = ndimage.minimum_filter(ok.astype(np.uint8), size=n + 4, mode="constant", cval=0)
    rows, cols = np.nonzero(free)
    assert len(rows), "no open ground on the tile"
    r, c = rows[len(rows) // 2], cols[len(cols) // 2]
    half = size_m / 2
    return shapely.box(x[c] - half, y[r] - half, x[c] + half, y[r] + half)


def test_ign_simulated_past(ign_footprints_run):
    run = ign_footprints_run
    city, ndsm = run.city, run.ndsm
    old, _ = read_footprints(shared(BDUNI), crs=CRS)
    standing = {b.id: b for b in city.buildings if b.status == "ok"}
    assert len(standing) >= 5
    by_id = {o.id: o for o in old}
    for bid, b in standing.items():  # a past database with heights: today's, before edits
        by_id[bid].attributes = {**by_id[bid].attributes, "roof_z": b.roof_z}
    ids = sorted(standing, key=lambda i: -standing[i].footprint.area)
    removed, raised, extended, split = ids[2], ids[0], ids[1], ids[3]
    expected = {i: "unchanged" for i in standing}
    expected.update({removed: "new", raised: "height_changed", extended: "footprint_changed"})
    # height: the old database 5 m lower
    by_id[raised].attributes["roof_z"] = standing[raised].roof_z - 5.0
    # footprint: the old outline a third smaller (the new one is an extension)
    p = by_id[extended].polygon
    smaller = affinity.scale(p, 2 / 3, 1, origin=(p.bounds[0], p.bounds[1]))
    by_id[extended] = Footprint(extended, smaller, by_id[extended].attributes)
    # split: two old parts for one building (not a change)
    p = by_id[split].polygon
    cx = p.centroid.x
    halves = [p.intersection(shapely.box(p.bounds[0] - 1, p.bounds[1] - 1, cx, p.bounds[3] + 1)),
              p.intersection(shapely.box(cx, p.bounds[1] - 1, p.bounds[2] + 1, p.bounds[3] + 1))]
    parts = [Footprint(f"{split}-{k}", h, by_id[split].attributes) for k, h in enumerate(halves)]
    fake = Footprint("fake", _open_ground(ndsm, [o.polygon for o in old]), {"roof_z": 190.0})
    past = [by_id[o.id] for o in old if o.id not in (removed, split)] + parts + [fake]
    expected["fake"] = "demolished"

    result = detect_changes(past, city, ndsm, units=run.units)

    truth, predicted = [], []
    for rec in result.changes:
        keys = [i.split("-")[0] if i.startswith(f"{split}-") else i for i in rec["old_ids"]]
        keys = keys or rec["new_ids"]
        want = {expected.get(k, "not_observed") for k in keys}
        want = (want - {"unchanged"}) or want  # a group with one changed member is that change
        assert len(want) == 1, rec
        truth.append(want.pop())
        predicted.append(rec["class"])
    truth, predicted = np.array(truth), np.array(predicted)
    classes = ("unchanged", "new", "demolished", "height_changed", "footprint_changed")
    for cls in (*classes, "not_observed"):
        tp = np.sum((truth == cls) & (predicted == cls))
        precision = tp / max(np.sum(predicted == cls), 1)
        recall = tp / max(np.sum(truth == cls), 1)
        assert precision == 1 and recall == 1, (cls, precision, recall, list(zip(truth, predicted)))
    # buildings off the tile are not demolished: no data is not no building
    assert result.summary["demolished"] == 1
    assert result.summary["not_observed"] == len(old) - len(standing)
    ext = next(r for r in result.changes if extended in r["old_ids"])
    assert ext["subtype"] == "extension" and ext["area_change"] > 0.3
    rais = next(r for r in result.changes if raised in r["old_ids"])
    assert rais["dh"] == pytest.approx(5.0, abs=0.01)
    for rec in result.changes:
        if rec["class"] in ("new", "demolished", "height_changed", "footprint_changed"):
            assert rec["confidence"] > 0.5, rec

    # with vegetation cover and point density as extra evidence: same classes
    share = getattr(run, "vegetation_share", None)
    vegetation = ndsm.like(share) if share is not None and share.shape == ndsm.shape else None
    density = point_density(run.cloud.xyz, ndsm)
    full = detect_changes(past, city, ndsm, units=run.units, vegetation=vegetation, density=density)
    assert [r["class"] for r in full.changes] == list(predicted)
    for rec in full.changes:
        if rec["class"] not in ("not_observed",):
            assert rec["density"] > 2 and rec["confidence"] > 0.5, rec


def test_ign_detected_buildings(ign_run):
    """BD Uni against detected buildings: every on-tile building matched, none demolished."""
    old, _ = read_footprints(shared(BDUNI), crs=CRS)
    result = detect_changes(old, ign_run.city, ign_run.ndsm, units=ign_run.units)
    assert result.summary["demolished"] == 0
    matched = {i for r in result.changes if r["new_ids"] for i in r["old_ids"]}
    observed = {i for r in result.changes if r["class"] != "not_observed" for i in r["old_ids"]}
    assert observed == matched and len(matched) >= 5
    assert result.summary["not_observed"] == len(old) - len(matched)
    # lidar outlines include eaves: within the shift tolerance, not every building differs
    assert result.summary["unchanged"] >= 1
    model = updated_model(old, ign_run.city, result)
    n_new = sum(len(r["new_ids"]) for r in result.changes)
    assert len(model.buildings) == len(old) - len(matched) + n_new


def test_synthetic_stereo_city_with_known_edits(tmp_path):
    """A rendered city reconstructed from stereo against its own truth map, edited to an earlier state.

    Every edit must be found and nothing else reported: precision and recall 1 for
    each class (the issue asks >= 95 %).
    """
    from recon3d.io.vectors import Footprint, read_footprints
    from recon3d.pipeline.run import run
    from recon3d.quality.change import detect_changes
    from recon3d.synthetic import write_scene

    scene = tmp_path / "scene"
    write_scene(scene, seed=0)
    state = run(scene, tmp_path / "out")
    truth, _ = read_footprints(scene / "truth" / "footprints.geojson", crs=state.city.crs)
    for f in truth:
        f.attributes.pop("roof_type", None)  # an old 2-D map: no roof types
    removed = {truth[0].id, truth[5].id}
    old = [f for f in truth if f.id not in removed]
    lowered = {f.id for f in old[1:3]}
    for f in old[1:3]:
        f.attributes["height"] -= 5.0
    shrunk = old[4]
    shrunk.polygon = shapely.affinity.scale(shrunk.polygon, 0.6, 0.6, origin=shrunk.polygon.centroid)
    lo, hi = state.cloud.bounds
    fakes = [Footprint(f"fake{i}", shapely.box(x - 4, y - 4, x + 4, y + 4), {"height": 8.0})
             for i, (x, y) in enumerate([(lo[0] + 8, lo[1] + 8), (hi[0] - 8, hi[1] - 8)])]
    result = detect_changes(old + fakes, state.city, state.ndsm, units=state.units)
    found = {c["class"]: [] for c in result.changes}
    for c in result.changes:
        found[c["class"]].append(c)
    assert {i for c in found["demolished"] for i in c["old_ids"]} == {"fake0", "fake1"}
    assert {i for c in found["height_changed"] for i in c["old_ids"]} == lowered
    assert {i for c in found["footprint_changed"] for i in c["old_ids"]} == {shrunk.id}
    truth_of_new = {f.id for f in truth if f.id in removed}
    new_polys = [c["geometry"] for c in found["new"]]
    hit = {f.id for f in truth if f.id in truth_of_new and any(p.intersects(f.polygon) for p in new_polys)}
    assert hit == truth_of_new and len(found["new"]) == len(truth_of_new)  # recall and precision 1
    assert not found.get("roof_changed")


# --------------------------------------------------------------------------- at the old database's granularity

#: Which class an old building gets when records disagree (a block's "unchanged"
#: record and its own height record): the more specific one.
_SEVERITY = {"unchanged": 0, "not_observed": 0, "roof_changed": 1, "footprint_changed": 1, "height_changed": 2,
             "new": 3, "demolished": 3}


def _town_scores(town, result) -> dict[str, tuple[int, int]]:
    """(found, expected) per edit kind, and (false changes, old buildings)."""
    per_old: dict[str, str] = {}
    for rec in result.changes:
        for i in rec["old_ids"]:
            if _SEVERITY[rec["class"]] >= _SEVERITY[per_old.get(i, "unchanged")]:
                per_old[i] = rec["class"]
    new = [r["geometry"] for r in result.changes if r["class"] == "new"]
    found = sum(any(g.intersection(h).area > 0.5 * h.area for g in new) for h in town.removed.values())
    spurious = sum(not any(g.intersection(h).area > 0.25 * g.area for h in town.removed.values()) for g in new)
    edited = town.raised | town.demolished
    false = sum(per_old.get(o.id, "unchanged") != "unchanged" for o in town.old if o.id not in edited) + spurious
    return {
        "new": (found, len(town.removed)),
        "raised": (sum(per_old.get(i) == "height_changed" for i in town.raised), len(town.raised)),
        "demolished": (sum(per_old.get(i) == "demolished" for i in town.demolished), len(town.demolished)),
        "false": (false, len(town.old)),
    }


@pytest.mark.parametrize("absolute, as_text", [(True, False), (False, True)])
def test_terraced_towns_changes_found_house_by_house(absolute, as_text):
    """Random terraced towns whose rows come out of detection as whole blocks: houses
    missing from the old database are new, houses raised since are height changes,
    outlines on open ground are demolished, whether the old ``roof_height`` is above
    the datum or above ground (decided from the data), numbers or text. Issue targets:
    recall >= 95 % for each, <= 5 % false changes (before: 0 % of the new and 0 % of
    the raised found, 12.6 % false changes)."""
    from recon3d.synthetic.terraces import RAISED_BY, terraced_town

    total = {k: [0, 0] for k in ("new", "raised", "demolished", "false")}
    for seed in range(5):
        town = terraced_town(seed, absolute=absolute, as_text=as_text)
        result = detect_changes(town.old, town.city, town.ndsm, vegetation=town.vegetation)
        for k, (a, b) in _town_scores(town, result).items():
            total[k][0] += a
            total[k][1] += b
        reference = "absolute" if absolute else "above ground"
        assert any(f"'roof_height' read as {reference}" in n for n in result.notes), result.notes
        assert not result.warnings
        raised = [r for r in result.changes if r["class"] == "height_changed"]
        assert raised and all(r["dh"] == pytest.approx(RAISED_BY, abs=0.5) for r in raised)
        model = updated_model(town.old, town.city, result)  # the blocks once each, not per record
        assert sorted(b.id for b in model.buildings if b.id.startswith("b")) == sorted(b.id for b in town.city)
    for kind in ("new", "raised", "demolished"):
        found, expected = total[kind]
        assert found >= 0.95 * expected, (kind, total)
    assert total["false"][0] <= 0.05 * total["false"][1], total


def test_old_heights_named_given_or_missing():
    """A height attribute of any name is read with --old-height-field (in feet when it
    says so); without one the user is warned, and nothing is reported as a height change."""
    from recon3d.synthetic.terraces import terraced_town

    town = terraced_town(7, absolute=False, field="hgt_2015")
    silent = detect_changes(town.old, town.city, town.ndsm, vegetation=town.vegetation)
    assert silent.summary["height_changed"] == 0
    assert any("no height attribute" in w and "--old-height-field" in w for w in silent.warnings)
    for o in town.old:
        o.attributes["hgt_2015"] = f"{float(o.attributes['hgt_2015']) / 0.3048:.2f} ft"
    named = detect_changes(town.old, town.city, town.ndsm, vegetation=town.vegetation,
                           config=ChangeParams(height_field="HGT_2015", height_reference="ground"))
    assert not named.warnings
    scores = _town_scores(town, named)
    assert scores["raised"][0] == scores["raised"][1] and scores["false"][0] == 0, scores
    wrong = detect_changes(town.old, town.city, town.ndsm, vegetation=town.vegetation,
                           config=ChangeParams(height_field="hgt_2015", height_reference="absolute"))
    assert any("differ from the data" in w for w in wrong.warnings)
    with pytest.raises(InputError, match="choose ground or absolute"):
        ChangeParams(height_reference="sea")


def test_ign_heights_as_roof_height_text(ign_footprints_run):
    """The real BD Uni outlines with ``roof_height`` as text above ground (today's
    heights, one building 5 m lower): read as above ground, the raised building found,
    nothing else changed."""
    run = ign_footprints_run
    old, _ = read_footprints(shared(BDUNI), crs=CRS)
    standing = {b.id: b for b in run.city.buildings if b.status == "ok"}
    raised = max(standing, key=lambda i: standing[i].footprint.area)
    for o in old:
        if o.id in standing:
            b = standing[o.id]
            o.attributes = {"roof_height": f"{b.roof_z - b.ground_z - (5.0 if o.id == raised else 0.0):.2f}"}
    result = detect_changes(old, run.city, run.ndsm, units=run.units)
    assert any("'roof_height' read as above ground" in n for n in result.notes), result.notes
    changed = {i: r["class"] for r in result.changes for i in r["old_ids"] if r["class"] not in ("unchanged", "not_observed")}
    assert changed == {raised: "height_changed"}
    assert next(r for r in result.changes if raised in r["old_ids"])["dh"] == pytest.approx(5.0, abs=0.01)
