"""Roof planes (buildings.roofs), LoD1.3 / LoD2.2 solids (buildings.lod) and roof accuracy
(quality.roofs).

Reference roofs come from real city models in ../shared/data/citymodels: their LoD2.2
roof surfaces are sampled into an airborne-LiDAR-like point cloud (8-20 points/m2,
5 cm noise, holes, a few wall points, ground around), the building is rebuilt from
its footprint and the points, and the result is compared with the original.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely
from conftest import shared

from recon3d.buildings import extrude, lod, partition
from recon3d.buildings.roofs import RoofParams, roof_type, segment_roof
from recon3d.config import LodConfig
from recon3d.core.city import Solid
from recon3d.core.geo import LocalFrame, Units
from recon3d.quality import roofs as roofq
from recon3d.quality.meshcheck import check_solid

CITYMODELS = ("citymodels/multi_lod.json", "citymodels/DH_01_subs.city.json", "citymodels/rotterdam_subset.json")
ALL_LODS = LodConfig(lods=("1", "1.3", "2.2"))
#: CityGML roof type codes (used by the Den Haag model) whose type is unambiguous.
CITYGML_ROOF_TYPES = {"1000": "flat", "1010": "shed", "1030": "gable", "1040": "hip", "1070": "pyramid"}


# --------------------------------------------------------------------------- reference models


def read_lod2(path) -> list[dict]:
    """LoD2 / LoD2.2 buildings of a CityJSON 1.1 or 2.0 file (a small test-only reader).

    Returns one dict per city object with a LoD2 geometry: ``id``, ``solid`` (a
    :class:`Solid` in world coordinates; a MultiSurface keeps its surfaces), ``closed``,
    ``footprint`` (union of the ground surfaces in plan), ``ground_z`` and
    ``roof_type`` when the file states an unambiguous one.
    """
    doc = json.loads(path.read_text(encoding="utf-8"))
    t = doc.get("transform", {"scale": [1, 1, 1], "translate": [0, 0, 0]})
    verts = np.asarray(doc["vertices"], dtype=np.float64) * t["scale"] + t["translate"]
    out = []
    for oid, obj in doc["CityObjects"].items():
        for geom in obj.get("geometry", []):
            if str(geom.get("lod")) not in ("2", "2.2"):
                continue
            sem = geom.get("semantics", {})
            kinds = [s["type"] for s in sem.get("surfaces", [])]
            if geom["type"] == "Solid":
                shell, values = geom["boundaries"][0], sem["values"][0]
            elif geom["type"] == "MultiSurface":
                shell, values = geom["boundaries"], sem["values"]
            else:
                continue
            surfaces = [[np.asarray(r) for r in face] for face in shell]
            semantics = [kinds[v] if v is not None else "WallSurface" for v in values]
            solid = Solid(verts, surfaces, semantics)
            ground = [
                shapely.Polygon(verts[f[0]][:, :2], [verts[r][:, :2] for r in f[1:]])
                for f, s in zip(surfaces, semantics, strict=True)
                if s == "GroundSurface"
            ]
            footprint = shapely.union_all([shapely.make_valid(g) for g in ground]) if ground else None
            if footprint is not None and footprint.geom_type != "Polygon":
                parts = [p for p in shapely.get_parts(footprint) if p.geom_type == "Polygon"]
                footprint = max(parts, key=lambda p: p.area) if parts else None
            ground_z = min(float(verts[f[0]][:, 2].min()) for f, s in zip(surfaces, semantics, strict=True) if s == "GroundSurface")
            attrs = obj.get("attributes", {})
            kind = CITYGML_ROOF_TYPES.get(str(attrs.get("roofType", "")))
            if attrs.get("dak_type") in ("single horizontal", "horizontal"):
                kind = "flat"
            out.append(
                {
                    "id": oid,
                    "solid": _compact(solid),
                    "closed": geom["type"] == "Solid",
                    "footprint": footprint,
                    "ground_z": ground_z,
                    "roof_type": kind,
                }
            )
    return out


def _compact(solid: Solid) -> Solid:
    used = np.unique(np.concatenate([r for s in solid.surfaces for r in s]))
    remap = np.full(len(solid.vertices), -1)
    remap[used] = np.arange(len(used))
    return Solid(solid.vertices[used], [[remap[r] for r in s] for s in solid.surfaces], list(solid.semantics))


def sample_building(ref: dict, rng: np.random.Generator, *, density=None, noise=0.05) -> np.ndarray:
    """An airborne-LiDAR-like cloud of one reference building (world coordinates).

    Roofs at ``density`` points/m2 in plan (8-20 drawn at random when None) with
    Gaussian height noise, two holes of 1-1.5 m radius (less on small buildings), walls at 1 point/m2, and
    ground points in a 5 m ring around the footprint.
    """
    dens = float(rng.uniform(8, 20)) if density is None else density
    mesh = ref["solid"].to_trimesh()
    sem = np.asarray(mesh.metadata["semantics"])
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    pts = []
    for kind, per_area, plan in (("RoofSurface", dens, True), ("WallSurface", 1.0, False)):
        t = tri[sem == kind]
        if not len(t):
            continue
        cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        area = 0.5 * (np.abs(cross[:, 2]) if plan else np.linalg.norm(cross, axis=1))
        count = rng.poisson(area * per_area)
        idx = np.repeat(np.arange(len(t)), count)
        r1, r2 = rng.random(len(idx)), rng.random(len(idx))
        flip = r1 + r2 > 1
        r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
        p = t[idx, 0] + r1[:, None] * (t[idx, 1] - t[idx, 0]) + r2[:, None] * (t[idx, 2] - t[idx, 0])
        if kind == "RoofSurface":
            top = roofq.roof_height_at(ref["solid"], p[:, :2])
            p = p[p[:, 2] >= top - 0.01]
        pts.append(p)
    cloud = np.concatenate(pts)
    cloud[:, 2] += rng.normal(0, noise, len(cloud))
    fp = ref["footprint"]
    x0, y0, x1, y1 = fp.bounds
    radius = min(1.0, 0.1 * np.sqrt(fp.area))
    for _ in range(2):
        c = rng.uniform([x0, y0], [x1, y1])
        cloud = cloud[np.hypot(cloud[:, 0] - c[0], cloud[:, 1] - c[1]) > radius * rng.uniform(1.0, 1.5)]
    ring = fp.buffer(5.0).difference(fp)
    gx0, gy0, gx1, gy1 = ring.bounds
    g = rng.uniform([gx0, gy0], [gx1, gy1], (int(ring.envelope.area * dens), 2))
    g = g[shapely.contains_xy(ring, g[:, 0], g[:, 1])]
    ground = np.column_stack([g, ref["ground_z"] + rng.normal(0, noise, len(g))])
    return np.concatenate([cloud, ground])


def rebuild(ref: dict, cloud: np.ndarray, config=ALL_LODS):
    """build_lods on a reference building; returns (result, frame, reference solid in the frame)."""
    frame = LocalFrame.around(ref["solid"].vertices.min(axis=0))
    fp = lod.clean_footprint(ref["footprint"], 0.01)
    inside = shapely.contains_xy(fp, cloud[:, 0], cloud[:, 1])
    roof_z = float(np.percentile(cloud[inside, 2], 90)) if inside.any() else float("nan")
    result = lod.build_lods(fp, cloud, ref["ground_z"], roof_z, frame, config)
    reference = Solid(frame.to_local(ref["solid"].vertices), ref["solid"].surfaces, ref["solid"].semantics)
    return result, frame, reference


@pytest.fixture(scope="module")
def reference_buildings():
    refs = []
    for name in CITYMODELS:
        refs += [dict(r, source=name) for r in read_lod2(shared(name)) if r["footprint"] is not None]
    return refs


@pytest.fixture(scope="module")
def rebuilt(reference_buildings):
    """Every reference building sampled and rebuilt once (seeded)."""
    rng = np.random.default_rng(2024)
    out = []
    for ref in reference_buildings:
        cloud = sample_building(ref, rng)
        result, frame, reference = rebuild(ref, cloud)
        local = frame.to_local(cloud)
        inside = shapely.contains_xy(
            shapely.transform(ref["footprint"], lambda c: c - np.asarray(frame.origin[:2])), local[:, 0], local[:, 1]
        )
        roof_pts = local[inside & (local[:, 2] > ref["ground_z"] - frame.origin[2] + 1.0)]
        out.append({"ref": ref, "result": result, "reference": reference, "cloud": local, "roof_points": roof_pts})
    return out


# --------------------------------------------------------------------------- reference roofs

#: Planes smaller than this (m2, plan view) are not counted in completeness/correctness:
#: with min_plane_area = 2 m2 and 8-20 points/m2 (some of them lost to the holes) they
#: cannot be found reliably.
MIN_PLANE_AREA = 3.0


def test_reference_roofs_rebuilt(rebuilt):
    """Every reference building gets a valid solid; the roofs match the reference models.

    Measured (this seed; 35 buildings of 3DBAG, Den Haag and Rotterdam): LoD2.2 for 34
    (the 35th is a 0.15 m2 chimney-like part without points: LoD1 + too_few_points);
    roof height RMS (ISPRS RMS_Z over corresponding planes) 0.000-0.041 m, median
    0.005 m; point-to-roof RMS 0.06-0.14 m; |volume error| <= 1.1 %; planes >= 3 m2:
    completeness 71/72, correctness 71/71 (all planes: 73/77 and 73/73). Seeds 1-3
    give the same picture (RMS_Z <= 0.041 m, completeness 100 %, volume <= 0.9 %).
    Over all grid points, step edges included, the height RMS is 0.1-0.6 m: on the
    Rotterdam blocks with 4-5 m height jumps 1-3 % of the roof area lies on the wrong
    side of a step wall (``misplaced_share``), which the ISPRS RMS_Z leaves to RMS_XY.
    """
    n22, heights, found, n_ref, correct, n_mod, volumes = 0, [], 0, 0, 0, 0, []
    for item in rebuilt:
        result = item["result"]
        assert result.solids, item["ref"]["id"]
        for lod_name, solid in result.solids.items():
            assert check_solid(solid) == [], (item["ref"]["id"], lod_name)
        if "2.2" not in result.solids:
            assert result.reason in lod.LOD_REASONS
            continue
        n22 += 1
        m = roofq.compare_roofs(
            item["reference"], result.solids["2.2"], volume=item["ref"]["closed"], min_area=MIN_PLANE_AREA
        )
        heights.append(m["height_rms"])
        found += m["n_found"]
        n_ref += m["n_reference"]
        correct += m["n_correct"]
        n_mod += m["n_model"]
        if item["ref"]["closed"]:
            volumes.append(m["volume_error"])
        assert result.roof_rms <= 0.25, item["ref"]["id"]
    heights = np.array([h for h in heights if np.isfinite(h)])
    assert n22 >= len(rebuilt) - 1
    assert np.all(heights <= 0.25), heights.max()
    assert found / n_ref >= 0.85, (found, n_ref)
    assert correct / n_mod >= 0.90, (correct, n_mod)
    assert np.max(np.abs(volumes)) <= 0.05


def test_reference_roof_types(rebuilt):
    """Roof types match where the reference states a clear one (Den Haag roofType codes,
    3DBAG 'single horizontal'), on buildings of at least 10 m2."""
    checked = 0
    for item in rebuilt:
        ref = item["ref"]
        if ref["roof_type"] is None or ref["footprint"].area < 10.0 or "2.2" not in item["result"].solids:
            continue
        checked += 1
        assert item["result"].roof_type == ref["roof_type"], ref["id"]
    assert checked >= 6


def test_roof_type_of_reference_planes(reference_buildings):
    """roof_type on planes taken from the reference models themselves."""
    from recon3d.buildings.roofs import RoofPlane

    seen = {}
    for ref in reference_buildings:
        if ref["footprint"].area < 10.0:
            continue
        planes = []
        for view in roofq.roof_planes(ref["solid"]):
            c = np.asarray(view.footprint.centroid.coords)[0]
            z = -(view.normal[:2] @ c + view.offset) / view.normal[2]
            plane = np.append(view.normal, view.offset)
            planes.append(RoofPlane(plane, np.zeros(0, int), 0.0, view.area, np.array([*c, z])))
        kind = roof_type(planes)
        if ref["roof_type"]:
            assert kind == ref["roof_type"], ref["id"]
        seen[kind] = seen.get(kind, 0) + 1
    assert seen.get("flat", 0) >= 5 and seen.get("gable", 0) >= 3


# --------------------------------------------------------------------------- synthetic roofs


def _synthetic(fun, footprint, *, density=12.0, noise=0.05, seed=1, origin=(85000.0, 447000.0, 0.0)):
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = footprint.bounds
    n = int((x1 - x0) * (y1 - y0) * density)
    xy = rng.uniform([x0, y0], [x1, y1], (n, 2))
    z = fun(xy[:, 0], xy[:, 1]) + rng.normal(0, noise, n)
    o = np.asarray(origin)
    pts = np.column_stack([xy, z]) + o
    return pts, shapely.transform(footprint, lambda c: c + o[:2]), LocalFrame.around(o)


ROOFS = {
    "gable": (lambda x, y: 10 - 0.6 * np.abs(x - 5), shapely.box(0, 0, 10, 20)),
    "hip": (lambda x, y: 10 - 0.6 * np.maximum(np.abs(x - 5), np.abs(y - 10) - 5), shapely.box(0, 0, 10, 20)),
    "pyramid": (lambda x, y: 10 - 0.6 * np.maximum(np.abs(x - 5), np.abs(y - 5)), shapely.box(0, 0, 10, 10)),
    "shed": (lambda x, y: 8 + 0.3 * x, shapely.box(0, 0, 10, 20)),
    "flat": (lambda x, y: 8 + 0 * x, shapely.box(0, 0, 10, 20)),
}


def test_conical_spire_is_stepped_by_height():
    """A noisy cone 18 m high over a square (no plane fits much of it): LoD2.2 is refused for low
    coverage and LoD1.3 steps up towards the tip by height levels, instead of the one
    or two flat slabs the few plane fragments would give."""
    def cone(x, y):
        return 18.0 - 1.7 * np.hypot(x - 5, y - 5)

    pts, fpw, frame = _synthetic(cone, shapely.box(0, 0, 10, 10), density=20.0, noise=0.4)
    result = lod.build_lods(fpw, pts, 0.0, 18.0, frame, ALL_LODS)
    assert "2.2" not in result.solids and result.reason == "low_coverage"
    solid = result.solids["1.3"]
    assert check_solid(solid) == []
    tops = {round(float(v), 1) for v in np.asarray(solid.vertices)[:, 2]} - {0.0}
    assert len(tops) >= 5, sorted(tops)  # a staircase, not a slab
    assert max(tops) > 14.0  # it reaches up the cone
    gx, gy = np.meshgrid(np.arange(0.05, 10, 0.1), np.arange(0.05, 10, 0.1))
    truth = float(cone(gx, gy).sum() * 0.01)
    assert abs(roofq.solid_volume(solid) / truth - 1) < 0.1


def test_narrow_eave_strip_stays_on_its_own_plane():
    """A flat roof at 12 m whose eave drops 1 m over a strip 0.7 m wide, beside an annex
    at 6 m: the strip is two cells of the label grid wide, and cleaning the grid must
    not hand its cells to the annex, which would put its points 5-6 m under the model
    (32 of 99 points more than 2 m low before the fit to the planes was checked)."""
    from affine import Affine

    from recon3d.core.city import Building, CityModel
    from recon3d.core.raster import Raster
    from recon3d.quality.rasterize import surface_at

    def roof(x, y):
        return np.where(x < 4.3, 12.0, np.where(x < 5.0, 12.0 - (x - 4.3) / 0.7, 6.0))

    pts, fpw, frame = _synthetic(roof, shapely.box(0, 0, 10, 12), density=16.0, noise=0.03)
    result = lod.build_lods(fpw, pts, 0.0, 12.0, frame, ALL_LODS)
    assert result.status == "ok"
    city = CityModel([Building("b", fpw, 0.0, 12.0, result.solids)], None, frame)
    o = np.asarray(frame.origin)
    dtm = Raster(np.zeros((30, 30), np.float32), Affine(1, 0, o[0] - 10, 0, -1, o[1] + 20))
    x, y = pts[:, 0] - o[0], pts[:, 1] - o[1]
    strip = (x > 4.3) & (x < 5.0) & (y > 1) & (y < 11)
    below = surface_at(city, pts[strip, 0], pts[strip, 1], dtm) - pts[strip, 2] < -2.0
    assert below.mean() < 0.1, below.sum()  # measured 5 of 99


def test_narrow_spire_keeps_its_top_terraces():
    """A tower 5 m wide whose spire rises 10 m above the eaves: the terraces near the tip
    cover well under 1 m2 each and must stay, or the spire is cut off metres below its
    tip (19.2 m of 22 m when terraces under 1 m2 went to their neighbours)."""
    def spire(x, y):
        return 22.0 - 4.0 * np.hypot(x - 2.5, y - 2.5)

    pts, fpw, frame = _synthetic(spire, shapely.box(0, 0, 5, 5), density=20.0, noise=0.1)
    result = lod.build_lods(fpw, pts, 0.0, 12.0, frame, ALL_LODS)
    solid = result.solids["1.3"]
    assert check_solid(solid) == []
    assert np.asarray(solid.vertices)[:, 2].max() > 20.5  # measured 20.9 m
    assert result.roof_rms < 0.55  # measured 0.52 m (0.56 without the top terraces)


@pytest.mark.parametrize("kind", sorted(ROOFS))
def test_synthetic_roof_types_and_volumes(kind):
    fun, fp = ROOFS[kind]
    pts, fpw, frame = _synthetic(fun, fp)
    result = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    assert result.status == "ok" and result.reason is None
    assert result.roof_type == kind
    solid = result.solids["2.2"]
    assert check_solid(solid) == []
    gx, gy = np.meshgrid(np.arange(0.05, fp.bounds[2], 0.1), np.arange(0.05, fp.bounds[3], 0.1))
    truth = float(fun(gx, gy).sum() * 0.01)
    assert abs(roofq.solid_volume(solid) / truth - 1) < 0.01
    assert result.roof_rms < 0.07
    kinds = {"gable": 7, "hip": 9, "shed": 6, "flat": 6}
    if kind in kinds:  # ground, roofs and one wall per footprint edge: no sliver surfaces
        assert len(solid.surfaces) == kinds[kind]


def test_semantics_and_orientation():
    fun, fp = ROOFS["gable"]
    pts, fpw, frame = _synthetic(fun, fp)
    solid = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS).solids["2.2"]
    from recon3d.core.city import newell_normal

    for rings, kind in zip(solid.surfaces, solid.semantics, strict=True):
        n = newell_normal(solid.vertices[rings[0]])
        n = n / np.linalg.norm(n)
        if kind == "GroundSurface":
            assert n[2] < -0.999
        elif kind == "WallSurface":
            assert abs(n[2]) < 1e-3
        else:
            assert n[2] > 0.5
    # local frame: the solid sits near the origin, not at national-grid coordinates
    assert np.abs(solid.vertices).max() < 1000


def test_step_wall_between_flat_roofs():
    """Two flat roofs 6 m apart in height meet at a vertical wall close to x = 5."""
    fun = lambda x, y: np.where(x < 5, 12.0, 6.0)  # noqa: E731
    pts, fpw, frame = _synthetic(fun, shapely.box(0, 0, 10, 20))
    solid = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS).solids["2.2"]
    walls = [
        solid.vertices[r[0]]
        for r, k in zip(solid.surfaces, solid.semantics, strict=True)
        if k == "WallSurface" and np.ptp(frame.to_world(solid.vertices[r[0]])[:, 0]) < 0.5
    ]
    inner = [w for w in walls if np.all(np.abs(frame.to_world(w)[:, 0] - 85000 - 5) < 0.5)]
    assert inner, "no step wall"
    x = frame.to_world(np.concatenate(inner))[:, 0] - 85000
    assert np.all(np.abs(x - 5) < 0.3)


def test_four_roofs_meeting_at_a_point():
    """Four flat roofs around one corner, heights going up and down around it: the four
    step walls would share one vertical edge (val3dity 304). The corner goes to one
    roof, leaving junctions of three, and LoD2.2 is built."""
    heights = np.array([[10.0, 11.0], [11.5, 10.5]])  # [y >= 10][x >= 10]
    fun = lambda x, y: heights[(y >= 10).astype(int), (x >= 10).astype(int)]  # noqa: E731
    pts, fpw, frame = _synthetic(fun, shapely.box(0, 0, 20, 20))
    result = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    assert "2.2" in result.solids, result.reason
    solid = result.solids["2.2"]
    assert check_solid(solid) == []
    tops = sorted({round(float(z), 1) for z in solid.vertices[:, 2]})
    assert tops == [0.0, 10.0, 10.5, 11.0, 11.5]


def test_roof_part_with_a_neck_snapping_would_close():
    """A roof part wraps a wedge-shaped part whose tip stops 2 mm short of the outline:
    snapping vertices (3 mm) would close that neck, the part would touch itself there
    and its walls would share a vertical edge four times (val3dity 304). The neck is
    opened first, and the solid is valid."""
    wedge = shapely.Polygon([(0, 4), (9.998, 5), (0, 6)])
    around = shapely.box(0, 0, 10, 10).difference(wedge)
    assert partition.necks([np.asarray(around.exterior.coords)[:-1]], 0.004).tolist() == [[9.998, 5.0]]
    planes = [np.array([0.0, 0.0, 1.0, -10.0]), np.array([0.0, 0.0, 1.0, -12.0])]
    regions = partition.open_pinches([(around, 0), (wedge, 1)], 0.05, 0.004)
    assert not any(len(partition.necks([partition.drop_close(np.asarray(p.exterior.coords)[:-1], 0.004)], 0.004)) for p, _ in regions)
    solid = extrude.partition_solid(regions, planes, 0.0, Units())
    assert check_solid(solid) == []


def test_pair_midpoints_of_labelled_points():
    """Midpoints of close points with different labels, grouped by label pair: the same
    groups as one mask per pair, and none (not a crash) when no two labels touch, as on
    a sparse stereo roof whose two planes lie apart (it cost a building its LoD2.2)."""
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 20, (400, 2))
    labels = np.where(rng.random(400) < 0.1, -1, (xy[:, 0] // 7).astype(int) + 3 * (xy[:, 1] > 10))
    got = partition._pair_midpoints(xy, labels, 1.0)
    keep = labels >= 0
    pts, lab = xy[keep], labels[keep]
    from scipy.spatial import cKDTree

    pairs = cKDTree(pts).query_pairs(1.5, output_type="ndarray")
    pairs = pairs[lab[pairs[:, 0]] != lab[pairs[:, 1]]]
    want = {}
    for i, j in pairs:
        want.setdefault((min(lab[i], lab[j]), max(lab[i], lab[j])), []).append(0.5 * (pts[i] + pts[j]))
    assert sorted(got) == sorted(want) and len(want) >= 5
    for key, mids in want.items():
        np.testing.assert_array_equal(got[key], np.array(mids))
    apart = np.array([[0.0, 0.0], [0.5, 0.0], [5.0, 0.0], [5.5, 0.0]])
    assert partition._pair_midpoints(apart, np.array([0, 0, 1, 1]), 1.0) == {}


def test_a_part_takes_the_plane_its_own_points_lie_on():
    """A 1 m2 speck labelled with a lower roof's plane, 13 m under the points it holds,
    takes the plane those points lie on (a stereo roof of the frame-survey family had
    such a pit, hidden from the robust roof RMS, which leaves out points over 1 m off);
    parts on their own plane, parts whose points no plane explains, and parts with
    too few points keep theirs."""
    high, low, shed = [0.0, 0.0, 1.0, -20.0], [0.0, 0.0, 1.0, -7.0], [-0.5, 0.0, np.sqrt(0.75), -10.0]
    planes = [np.array(p) for p in (high, low, shed)]
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 10, (2000, 2))
    z = np.where(xy[:, 0] < 8, 20.0, 7.0) + rng.normal(0, 0.05, len(xy))
    z[(xy[:, 0] > 2) & (xy[:, 0] < 3) & (xy[:, 1] > 2) & (xy[:, 1] < 3)] += 40.0  # a mast: no plane there
    points = np.column_stack([xy, z])
    speck = shapely.box(5, 5, 6, 6)
    mast = shapely.box(2, 2, 3, 3)
    tiny = shapely.box(6.5, 1, 6.6, 1.1)
    main = shapely.box(0, 0, 8, 10).difference(shapely.union_all([speck, mast, tiny]))
    regions = [(main, 0), (speck, 1), (mast, 1), (tiny, 1), (shapely.box(8, 0, 10, 10), 1)]
    got = partition.refit_parts(regions, planes, points, 1.0)
    assert [label for _, label in got] == [0, 0, 1, 1, 1]
    assert [poly for poly, _ in got] == [poly for poly, _ in regions]


def test_invalid_lod22_is_retried_without_small_parts(monkeypatch):
    """A LoD2.2 shell that fails the mesh check is built once more with the parts under
    a 2 x 2 block of grid cells merged, before falling back to LoD1.3 (on a 4 x 4
    tiling of the Delft strip this saved the last of 133 buildings)."""
    calls = []
    original = lod._roofed

    def failing_first(*args, coarse=False, **kwargs):
        calls.append(coarse)
        if kwargs.get("intersect") and not coarse:
            raise lod.LodFailure("invalid_mesh", "304 simulated")
        return original(*args, coarse=coarse, **kwargs)

    monkeypatch.setattr(lod, "_roofed", failing_first)
    fun, fp = ROOFS["hip"]
    pts, fpw, frame = _synthetic(fun, fp)
    result = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    assert calls[:2] == [False, True]
    assert result.status == "ok" and "2.2" in result.solids and result.roof_type == "hip"


def test_determinism_and_order_independence():
    fun, fp = ROOFS["hip"]
    pts, fpw, frame = _synthetic(fun, fp)
    a = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    b = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    c = lod.build_lods(fpw, pts[np.random.default_rng(7).permutation(len(pts))], 0.0, 9.0, frame, ALL_LODS)
    for other in (b, c):
        assert sorted(other.solids) == sorted(a.solids)
        for key, solid in a.solids.items():
            assert np.array_equal(solid.vertices, other.solids[key].vertices)
            assert len(solid.surfaces) == len(other.solids[key].surfaces)
            for s1, s2 in zip(solid.surfaces, other.solids[key].surfaces, strict=True):
                assert all(np.array_equal(r1, r2) for r1, r2 in zip(s1, s2, strict=True))
            assert solid.semantics == other.solids[key].semantics
        assert [p.plane.tolist() for p in other.planes] == [p.plane.tolist() for p in a.planes]


def test_segment_roof_seeded_planes():
    """Planes are found, regularised (symmetric gable: equal slopes, opposite aspects) and
    their inliers cover the roof."""
    fun, fp = ROOFS["gable"]
    pts, _, _ = _synthetic(fun, fp, origin=(0.0, 0.0, 0.0))
    seg = segment_roof(pts, RoofParams(), footprint=fp)
    assert len(seg.planes) == 2 and seg.coverage > 0.95
    a, b = seg.planes
    assert a.slope == pytest.approx(b.slope)
    assert abs((a.azimuth - b.azimuth) % 360 - 180) < 1e-9
    assert a.slope == pytest.approx(np.degrees(np.arctan(0.6)), abs=1.0)
    assert seg.rms < 0.07


def _matched_gable_under_a_crown(seed: int = 1, density: float = 200.0):
    """A gable roof as dense image matching gives it (``density`` points/m2), a fifth of
    it under a tree crown matched at four times that density at every height of the
    crown: (world points, world footprint, frame)."""
    fun, fp = ROOFS["gable"]
    pts, fpw, frame = _synthetic(fun, fp, density=density, seed=seed)
    rng = np.random.default_rng(seed + 1)
    centre, radius = np.array([8.0, 16.0]), 5.0
    m = int(np.pi * radius**2 * density * 4)
    angle, reach = rng.uniform(0, 2 * np.pi, m), radius * np.sqrt(rng.random(m))
    xy = centre + np.column_stack([reach * np.cos(angle), reach * np.sin(angle)])
    z = 12.0 + np.sqrt(radius**2 - reach**2) * rng.uniform(-0.8, 1.0, m)
    crown = np.column_stack([xy, z])[shapely.contains_xy(fp, xy[:, 0], xy[:, 1])]
    return np.concatenate([pts, crown + np.asarray(frame.origin)]), fpw, frame


def test_dense_matched_roof_under_a_crown_is_lod22(monkeypatch):
    """A photogrammetric cloud (200 points/m2, a crown matched at several heights over a
    fifth of the roof) is thinned to MAX_ROOF_DENSITY on a fixed grid before the roof is
    modelled: the crown's stacked points no longer outnumber the roof's (with every
    point, less than half lay on a plane: low_coverage, LoD1.3), and the partition's
    work no longer grows with the matcher's density."""
    pts, fpw, frame = _matched_gable_under_a_crown()
    from recon3d.buildings import roofs

    seen, real = [], roofs.segment_roof

    def spy(points, *args, **kwargs):
        seen.append(len(points))
        return real(points, *args, **kwargs)

    monkeypatch.setattr(roofs, "segment_roof", spy)
    result = lod.build_lods(fpw, pts, 0.0, 10.0, frame, ALL_LODS)
    _all_valid(result)
    assert result.status == "ok" and result.roof_type == "gable", (result.status, result.reason)
    assert result.roof_rms < 0.15
    assert len(seen) == 1 and seen[0] <= 1.05 * lod.MAX_ROOF_DENSITY * fpw.area  # of 84,000 (cells on the rim)
    # a point order of its own gives the same solids (the thinning takes each cell's first point in sorted order)
    again = lod.build_lods(fpw, pts[np.random.default_rng(3).permutation(len(pts))], 0.0, 10.0, frame, ALL_LODS)
    for key, solid in result.solids.items():
        assert np.array_equal(solid.vertices, again.solids[key].vertices)


# --------------------------------------------------------------------------- bad input


def _all_valid(result):
    assert result.status in ("ok", "fallback", "failed")
    if result.status != "ok":
        assert result.reason in lod.LOD_REASONS
    for solid in result.solids.values():
        assert check_solid(solid) == []


def test_handful_of_points():
    fun, fp = ROOFS["gable"]
    pts, fpw, frame = _synthetic(fun, fp)
    result = lod.build_lods(fpw, pts[:6], 0.0, 9.0, frame, ALL_LODS)
    _all_valid(result)
    assert result.status == "fallback" and result.reason == "too_few_points"
    assert "1" in result.solids


def test_no_points_and_no_height():
    fun, fp = ROOFS["flat"]
    _, fpw, frame = _synthetic(fun, fp)
    result = lod.build_lods(fpw, np.zeros((0, 3)), 0.0, float("nan"), frame, ALL_LODS)
    assert result.status == "failed" and result.reason == "no_points" and not result.solids


def test_footprint_with_courtyard():
    outer = shapely.box(0, 0, 30, 30)
    fp = outer.difference(shapely.box(10, 10, 20, 20))
    fun = lambda x, y: 6 + 0.5 * np.minimum.reduce([x, y, 30 - x, 30 - y]) * 0  # noqa: E731
    pts, fpw, frame = _synthetic(fun, fp)
    inside = shapely.contains_xy(fpw, pts[:, 0], pts[:, 1])
    result = lod.build_lods(fpw, pts[inside], 0.0, 6.0, frame, ALL_LODS)
    _all_valid(result)
    assert result.status == "ok"
    ground = [s for s, k in zip(result.solids["2.2"].surfaces, result.solids["2.2"].semantics, strict=True)
              if k == "GroundSurface"]
    assert len(ground) == 1 and len(ground[0]) == 2  # outer ring and the courtyard
    assert roofq.solid_volume(result.solids["2.2"]) == pytest.approx(6.0 * 800, rel=0.01)


def test_collinear_and_duplicate_vertices():
    fun, _ = ROOFS["gable"]
    fp = shapely.Polygon([(0, 0), (5, 0), (5, 0), (10, 0), (10, 10), (10, 20), (10, 20), (0, 20), (0, 10)])
    pts, fpw, frame = _synthetic(fun, fp)
    result = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    _all_valid(result)
    assert result.status == "ok"


def test_roof_of_forty_small_planes():
    """A roof of 40 tilted 2.5 x 2 m tiles: too many planes for LoD2.2 -> LoD1.3 or a
    valid LoD2.2, never an invalid mesh."""
    rng = np.random.default_rng(3)
    tilt = rng.uniform(-0.5, 0.5, (8, 5, 2))

    def fun(x, y):
        i = np.clip((x / 2.5).astype(int), 0, 7)
        j = np.clip((y / 2.0).astype(int), 0, 4)
        return 8 + tilt[i, j, 0] * (x - 2.5 * i) + tilt[i, j, 1] * (y - 2.0 * j) + (i + j) % 3

    pts, fpw, frame = _synthetic(fun, shapely.box(0, 0, 20, 10), density=20)
    result = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    _all_valid(result)
    assert result.solids


@pytest.mark.parametrize(
    "fp, height", [(shapely.box(0, 0, 2, 2), 1.0), (shapely.box(0, 0, 12, 12), 300.0), (shapely.box(0, 0, 0.3, 40), 5.0)]
)
def test_tiny_tall_and_thin_buildings(fp, height):
    fun = lambda x, y: height + 0.1 * x  # noqa: E731
    pts, fpw, frame = _synthetic(fun, fp, density=15)
    result = lod.build_lods(fpw, pts, 0.0, height, frame, ALL_LODS)
    _all_valid(result)
    assert result.solids


def test_degenerate_footprint():
    frame = LocalFrame()
    line = shapely.Polygon([(0, 0), (10, 0), (20, 0)])
    result = lod.build_lods(line, np.zeros((0, 3)), 0.0, 5.0, frame, ALL_LODS)
    assert result.status == "failed" and result.reason == "degenerate_footprint"


def test_lod_config_defaults_roundtrip():
    cfg = LodConfig()
    assert cfg.plane_distance > 0 and cfg.max_planes >= 10
    params = RoofParams.from_config(cfg)
    assert params.distance == cfg.plane_distance and params.seed == cfg.seed


# --------------------------------------------------------------------------- real LiDAR


def _lidar_buildings(state):
    xyz = state.cloud.xyz
    for b in state.city.buildings:
        x0, y0, x1, y1 = b.footprint.bounds
        m = (xyz[:, 0] >= x0) & (xyz[:, 0] <= x1) & (xyz[:, 1] >= y0) & (xyz[:, 1] <= y1)
        yield b, lod.build_lods(b.footprint, xyz[m], b.ground_z, b.roof_z, state.city.frame, ALL_LODS, units=state.units)


@pytest.mark.parametrize("fixture", ["delft_run", "ign_footprints_run"])
def test_real_lidar_buildings(fixture, request):
    """Every building gets a solid or a reason, all solids are valid, LoD2.2 roofs fit
    their points (robust RMS, points more than 1 m off left out) within 0.3 m.

    Measured: Delft 9 of 10 LoD2.2 in the pipeline (a spire with 16 % of its points on
    planes: LoD1.3), robust roof RMS 0.06-0.23 m; IGN
    village 6/6 LoD2.2 among the footprints with points (34 lie outside the data),
    0.04-0.10 m. The plain RMS over all roof points is 0.04-1.7 m: 0-27 % of them lie
    more than 1 m off the roof (overhanging trees, chimneys, wall points).
    """
    state = request.getfixturevalue(fixture)
    n22 = 0
    for b, result in _lidar_buildings(state):
        _all_valid(result)
        if not result.solids:
            assert result.reason in ("no_points", "too_low", "degenerate_footprint"), b.id
            continue
        if "2.2" in result.solids:
            n22 += 1
            assert result.roof_rms <= 0.3 / state.units.vertical, b.id
    assert n22 >= 5
    if fixture == "delft_run":  # a spike left by vertex insertion once cost one of them
        assert sum("2.2" in b.solids for b in state.city) >= 9


def test_validity_per_lod_names_the_failed_check(monkeypatch):
    """Each LoD tried carries its check's result (issue 19 item 6): "valid" for the
    solids built, and val3dity's codes for a LoD the check threw out. A gable whose
    pitched LoD2.2 the check is made to refuse (203, non-planar) falls back to LoD1.3,
    and its validity says why."""
    from recon3d.quality.meshcheck import MeshIssue
    from recon3d.quality.roofs import validity_attributes

    fun, fp = ROOFS["gable"]
    pts, fpw, frame = _synthetic(fun, fp)
    clean = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    assert clean.validity == {"1": (), "1.3": (), "2.2": ()}
    assert validity_attributes(clean.validity) == {"validity_lod1": "valid", "validity_lod13": "valid", "validity_lod22": "valid"}

    real = lod._issues

    def refuse_pitched(solid, u):
        pitched = any(kind == "RoofSurface" and abs(_normal_z(solid, i)) < 0.99
                      for i, kind in enumerate(solid.semantics))
        return [MeshIssue(203, "NON_PLANAR_POLYGON_DISTANCE_PLANE", "planted", 0)] if pitched else real(solid, u)

    monkeypatch.setattr(lod, "_issues", refuse_pitched)
    result = lod.build_lods(fpw, pts, 0.0, 9.0, frame, ALL_LODS)
    assert result.status == "fallback" and result.reason == "invalid_mesh"
    assert set(result.solids) == {"1", "1.3"}
    assert result.validity == {"1": (), "1.3": (), "2.2": (203,)}
    assert validity_attributes(result.validity)["validity_lod22"] == "203 NON_PLANAR_POLYGON_DISTANCE_PLANE"


def _normal_z(solid: Solid, i: int) -> float:
    from recon3d.core.mesh import newell_normal

    ring = np.asarray(solid.vertices)[solid.surfaces[i][0]]
    n = newell_normal(ring)
    return float(n[2] / (np.linalg.norm(n) or 1.0))
