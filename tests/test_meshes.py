"""Building meshes of the GLB and OBJ exports: closed shells for trimesh and manifold3d.

Each building's mesh, loaded as stored (nothing merged), must be watertight,
consistently wound, outward (positive volume) and accepted by manifold3d, and
enclose the volume of its CityJSON solid; T-junctions between polygons (a vertex of
one polygon inside another's edge) and the collinear ring vertices earcut drops
next to holes are where meshes used to open.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from conftest import shared
from shapely.geometry import box

from recon3d.cli import cli
from recon3d.core.city import Building, CityModel, Solid
from recon3d.core.geo import LocalFrame
from recon3d.core.mesh import (
    newell_normal,
    points_on_segments,
    solid_mesh,
    split_ring_edges,
    triangulate_surface,
    triangulate_surfaces,
)
from recon3d.io.cityjson import read_cityjson
from recon3d.io.gltf import write_glb
from recon3d.io.obj import write_obj
from recon3d.quality.meshcheck import check_mesh, check_mesh_file, check_solid, manifold_status

ORIGIN = (594000.0, 5765000.0, 0.0)
RUNS = ["delft_run", "ign_run", "ign_footprints_run"]


def polygon_volume(solid: Solid) -> float:
    """Volume of a closed polygon solid without triangulating it: sum over rings of c . N / 6.

    N is the ring's Newell normal (twice its vector area), c the mean of its points,
    so holes (wound the other way) subtract; exact for planar surfaces.
    """
    rings = [solid.vertices[r] for surface in solid.surfaces for r in surface]
    return float(sum(r.mean(axis=0) @ newell_normal(r) for r in rings)) / 6.0


def quads(vertices: np.ndarray, *rings: list[int]) -> list[list[np.ndarray]]:
    """Surfaces of one ring each."""
    return [[np.asarray(r)] for r in rings]


def stepped_box() -> Solid:
    """A 10 x 10 x 5 box with a 5 x 5 x 3 box on its corner, sharing the walls x = 0 and y = 0.

    Each box keeps its own wall quads, so the small box's wall corners (0, 5, 5) and
    (5, 0, 5) lie inside the big walls' top edges: two T-junctions. Volume 575.
    """
    v = np.array(
        [
            [0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0],  # 0-3 ground
            [0, 0, 5], [10, 0, 5], [10, 10, 5], [0, 10, 5],  # 4-7 big box top corners
            [5, 0, 5], [5, 5, 5], [0, 5, 5],  # 8-10 small box base on the big top
            [0, 0, 8], [5, 0, 8], [5, 5, 8], [0, 5, 8],  # 11-14 small box top
        ],
        float,
    )
    surfaces = quads(
        v,
        [0, 3, 2, 1],  # ground
        [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7],  # big walls: top edges unsplit
        [8, 5, 6, 7, 10, 9],  # big roof, an L around the small box
        [4, 8, 12, 11], [8, 9, 13, 12], [9, 10, 14, 13], [10, 4, 11, 14],  # small walls
        [11, 12, 13, 14],  # small roof
    )
    semantics = ["GroundSurface"] + ["WallSurface"] * 4 + ["RoofSurface"] + ["WallSurface"] * 4 + ["RoofSurface"]
    return Solid(v, surfaces, semantics)


def split_wall_box() -> Solid:
    """A 10 x 6 x 4 box whose wall y = 0 is two quads: its middle vertices split the roof and ground edges.

    Volume 240.
    """
    v = np.array(
        [[0, 0, 0], [10, 0, 0], [10, 6, 0], [0, 6, 0], [0, 0, 4], [10, 0, 4], [10, 6, 4], [0, 6, 4], [4, 0, 0], [4, 0, 4]],
        float,
    )
    surfaces = quads(
        v, [0, 3, 2, 1], [4, 5, 6, 7], [0, 8, 9, 4], [8, 1, 5, 9], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]
    )
    return Solid(v, surfaces, ["GroundSurface", "RoofSurface"] + ["WallSurface"] * 5)


def courtyard_with_collinear_vertices() -> Solid:
    """A 12 x 12 x 6 block around a 4 x 4 courtyard, every outer wall split in two quads.

    Edge-matched (val3dity-valid): the roof and ground rings hold the walls' middle
    vertices, collinear ones that earcut drops when it joins the courtyard hole.
    Volume (144 - 16) * 6 = 768.
    """
    outer = np.array([[0, 0], [6, 0], [12, 0], [12, 6], [12, 12], [6, 12], [0, 12], [0, 6]], float)
    inner = np.array([[4, 4], [4, 8], [8, 8], [8, 4]], float)  # clockwise from above
    xy = np.vstack([outer, inner])
    n = len(xy)
    v = np.vstack([np.column_stack([xy, np.zeros(n)]), np.column_stack([xy, np.full(n, 6.0)])])
    o, h = np.arange(8), np.arange(8, 12)
    surfaces = [[o[::-1], h[::-1]], [o + n, h + n]]  # ground (seen from below), roof
    for ring in (o, h):
        for a, b in zip(ring, np.roll(ring, -1), strict=True):
            surfaces.append([np.array([a, b, b + n, a + n])])
    return Solid(v, surfaces, ["GroundSurface", "RoofSurface"] + ["WallSurface"] * (len(surfaces) - 2))


SOLIDS = {"stepped_box": (stepped_box, 575.0), "split_wall": (split_wall_box, 240.0),
          "courtyard": (courtyard_with_collinear_vertices, 768.0)}


def city_of(*solids: Solid) -> CityModel:
    buildings = [Building(f"b{i}", box(0, 0, 1, 1), solids={"2.2": s}) for i, s in enumerate(solids)]
    return CityModel(buildings, None, LocalFrame(ORIGIN))


def assert_closed(mesh: trimesh.Trimesh, expected_volume: float, rel: float = 1e-9) -> None:
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(expected_volume, rel=rel)
    assert manifold_status(mesh.vertices, mesh.faces) == "NoError"


# --------------------------------------------------------------------------- the shared mesh builder


@pytest.mark.parametrize("name", sorted(SOLIDS))
def test_solid_mesh_is_closed_without_t_junctions(name):
    make, volume = SOLIDS[name]
    solid = make()
    assert polygon_volume(solid) == pytest.approx(volume, rel=1e-12)
    assert_closed(solid.to_trimesh(), volume)
    mesh = solid.mesh()
    assert len(np.unique(mesh.vertices, axis=0)) == len(mesh.vertices)  # one vertex per position
    edges = np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]])
    segment, _, _ = points_on_segments(mesh.vertices, mesh.vertices[edges[:, 0]], mesh.vertices[edges[:, 1]], 1e-6)
    assert not len(segment)  # no vertex inside any triangle edge


def test_t_junction_solids_were_open_before_the_split():
    """The constructed solids really have the defects: ring edges used once, or earcut dropping vertices."""
    assert {i.code for i in check_solid(stepped_box())} == {302}
    assert {i.code for i in check_solid(split_wall_box())} == {302}
    courtyard = courtyard_with_collinear_vertices()
    assert not check_solid(courtyard)  # edge-matched polygons ...
    import mapbox_earcut

    roof = courtyard.surfaces[1]
    xy = courtyard.vertices[np.concatenate(roof)][:, :2]
    tri = mapbox_earcut.triangulate_float64(xy, np.cumsum([len(r) for r in roof]).astype(np.uint32))
    assert len(np.unique(tri)) < len(xy)  # ... whose roof earcut alone triangulates without some vertices


def test_a_nearly_straight_shared_vertex_leaves_no_sliver_twice():
    """A 10 m cube whose roof and front wall share their edge through a vertex 10 um off
    the straight line (beyond the fold test, within the weld): for 4 of the 25 ring
    starts earcut cuts that vertex's sliver off both surfaces (the Delft strip met one
    when the DTM under a block moved). The pair cancels; the mesh must stay watertight."""
    eps = 1e-5
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [0, 0, 10], [10, 0, 10], [10, 10, 10],
                  [0, 10, 10], [5, -eps, 10 + eps]], float)
    for roof_start in range(5):
        for wall_start in range(5):
            roof, front = np.roll([4, 8, 5, 6, 7], roof_start), np.roll([0, 1, 5, 8, 4], wall_start)
            solid = Solid(v, quads(v, [0, 3, 2, 1], roof, front, [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]),
                          ["GroundSurface", "RoofSurface"] + ["WallSurface"] * 4)
            mesh = solid.to_trimesh()
            assert mesh.is_watertight and mesh.is_winding_consistent, (roof_start, wall_start)
            assert mesh.volume == pytest.approx(1000.0, abs=1e-3)
            assert manifold_status(mesh.vertices, mesh.faces) == "NoError"


def test_triangle_check_sees_what_the_polygon_check_cannot():
    """A closed polygon shell whose triangles are not closed (a sliver twice, one way and
    back, as earcut made before the pair was cancelled) fails the export check only."""
    from recon3d.core.mesh import SolidMesh
    from recon3d.quality.meshcheck import triangle_issues

    solid = stepped_box()
    solid = Solid(solid.vertices, solid.surfaces, solid.semantics)
    good = solid.mesh()
    assert not triangle_issues(solid)
    twice = np.array([[good.faces[0, 0], good.faces[0, 1], good.faces[1, 2]]])
    solid._mesh = SolidMesh(good.vertices, np.concatenate([good.faces, twice, twice[:, ::-1]]),
                            np.r_[good.surface, 0, 1])
    assert {i.code for i in triangle_issues(solid)} == {304}
    assert not solid.to_trimesh().is_watertight


def test_split_ring_edges_inserts_in_order():
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [7, 0, 0], [2, 0, 0], [5, 0.0004, 0], [5, 1, 0]], float)
    (ring,) = split_ring_edges(v, [np.array([0, 1, 2])], 1e-3)
    assert ring.tolist() == [0, 4, 5, 3, 1, 2]  # 1 mm tolerance takes (5, 0.4 mm), not (5, 1 m)


def test_welding_merges_close_vertices_and_keeps_the_first():
    solid = split_wall_box()
    v = solid.vertices.copy()
    v = np.vstack([v, v[9] + [0.0003, 0.0, -0.0002]])  # a copy of the wall's top middle vertex, 0.4 mm off
    surfaces = [[r.copy() for r in s] for s in solid.surfaces]
    surfaces[3][0][3] = 10  # the second wall quad uses the copy
    mesh = Solid(v, surfaces, solid.semantics).mesh()
    assert len(mesh.vertices) == 10
    np.testing.assert_array_equal(mesh.vertices, solid.mesh().vertices)
    assert_closed(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False), 240.0)


def test_flat_and_open_solids_give_no_or_open_meshes():
    flat = Solid(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), [[np.array([0, 1, 2])]], ["RoofSurface"])
    assert solid_mesh(flat.vertices, flat.surfaces).faces.shape == (0, 3)
    cube = split_wall_box()
    open_box = Solid(cube.vertices, cube.surfaces[1:], cube.semantics[1:])  # no ground
    mesh = open_box.to_trimesh()
    assert not mesh.is_watertight and manifold_status(mesh.vertices, mesh.faces) != "NoError"


def test_surfaces_triangulated_together_are_each_surface_triangulated_alone():
    """The batched triangulation repairs only the surfaces that need it, each as alone."""
    solids = [stepped_box(), split_wall_box(), courtyard_with_collinear_vertices()]
    for solid in solids:
        surfaces = split_ring_edges(solid.vertices, [r for s in solid.surfaces for r in s], 1e-3)
        rings = iter(surfaces)
        surfaces = [[next(rings) for _ in s] for s in solid.surfaces] + [[]]  # and one without rings
        faces, surface = triangulate_surfaces(solid.vertices, surfaces)
        alone = [triangulate_surface(solid.vertices, s) if s else np.zeros((0, 3), np.int64) for s in surfaces]
        np.testing.assert_array_equal(faces, np.concatenate(alone))
        np.testing.assert_array_equal(surface, np.repeat(np.arange(len(alone)), [len(t) for t in alone]))
        assert any(len(np.unique(t)) > 3 for t in alone)  # repaired surfaces are among them


def test_a_wall_at_45_degrees_is_triangulated_the_same_wherever_it_stands():
    """|nx| and |ny| of its normal are equal up to rounding, which depends on where the
    wall stands and on numpy's summation kernel: the projection plane (and so earcut's
    triangles) must not follow the last bit."""
    wall = np.array([[0, 0, 0], [3, -3, 0], [3, -3, 4], [1.5, -1.5, 3], [0, 0, 4]], float)
    results = set()
    for ox in np.arange(0.1, 3, 0.37):
        for oy in np.arange(0.2, 3, 0.41):
            tri = triangulate_surface(wall + [ox, oy, 0.3], [np.arange(5)])
            assert len(tri) == 3
            results.add(tri.tobytes())
    assert len(results) == 1


# --------------------------------------------------------------------------- GLB and OBJ of constructed solids


def test_exports_of_t_junction_solids_are_closed(tmp_path):
    solids = [make() for make, _ in SOLIDS.values()]
    volumes = [v for _, v in SOLIDS.values()]
    city = city_of(*solids)
    write_glb(city, tmp_path / "b.glb")
    write_obj(city, tmp_path / "b.obj")
    for name in ("b.glb", "b.obj"):
        checks = check_mesh_file(tmp_path / name)
        assert [c.id for c in checks] == ["b0", "b1", "b2"]
        assert all(c.ok and c.kind == "Solid" for c in checks), checks
        for c, volume in zip(checks, volumes, strict=True):
            assert c.volume == pytest.approx(volume, rel=1e-6)
    # the same bytes from a fresh model
    again = tmp_path / "again"
    write_glb(city_of(*(make() for make, _ in SOLIDS.values())), again / "b.glb")
    write_obj(city_of(*(make() for make, _ in SOLIDS.values())), again / "b.obj")
    for name in ("b.glb", "b.obj", "b.mtl"):
        assert (again / name).read_bytes() == (tmp_path / name).read_bytes()


def test_glb_keeps_surface_types_in_one_primitive(tmp_path):
    solid = stepped_box()
    write_glb(city_of(solid), tmp_path / "b.glb")
    scene = trimesh.load(tmp_path / "b.glb")
    (mesh,) = scene.geometry.values()
    ranges = mesh.metadata["surface_types"]
    assert list(ranges) == ["GroundSurface", "WallSurface", "RoofSurface"]
    assert sum(c for _, c in ranges.values()) == len(mesh.faces)
    up = mesh.face_normals[slice(ranges["RoofSurface"][0], sum(ranges["RoofSurface"]))]
    np.testing.assert_allclose(up, [[0, 1, 0]] * len(up), atol=1e-6)  # roofs face +Y (glTF up)
    assert mesh.metadata["geometry_type"] == "Solid"


def test_obj_one_object_and_material_per_building_with_surface_groups(tmp_path):
    city = city_of(*(make() for make, _ in SOLIDS.values()))
    write_obj(city, tmp_path / "b.obj")
    text = (tmp_path / "b.obj").read_text(encoding="utf-8")
    assert [line for line in text.splitlines() if line.startswith("o ")] == ["o b0", "o b1", "o b2"]
    first = text[text.index("o b0") : text.index("o b1")]
    assert [line for line in first.splitlines() if line.startswith(("usemtl", "g "))] == [
        "usemtl b0", "g b0_ground", "g b0_wall", "g b0_roof"]
    for options in ({}, {"split_objects": True, "group_material": False}):  # trimesh's default, and by object
        per_building = trimesh.load(tmp_path / "b.obj", process=False, **options)
        assert sorted(per_building.geometry) == ["b0", "b1", "b2"], options
        assert all(m.is_watertight for m in per_building.geometry.values()), options
    surfaces = trimesh.load(tmp_path / "b.obj", split_groups=True, group_material=False, process=False)
    assert sorted(surfaces.geometry) == sorted(f"b{i}_{k}" for i in range(3) for k in ("ground", "wall", "roof"))


def test_multisurface_is_exported_as_faces_and_not_checked(tmp_path):
    solid = split_wall_box()
    open_box = Solid(solid.vertices, solid.surfaces[1:], solid.semantics[1:], kind="MultiSurface")
    city = city_of(stepped_box(), open_box)
    write_glb(city, tmp_path / "b.glb")
    write_obj(city, tmp_path / "b.obj")
    for name in ("b.glb", "b.obj"):
        checks = check_mesh_file(tmp_path / name)
        assert [c.kind for c in checks] == ["Solid", "MultiSurface"]
        assert all(c.ok for c in checks) and not checks[1].watertight
    result = CliRunner().invoke(cli, ["validate", "--meshes", str(tmp_path / "b.glb")])
    assert result.exit_code == 0, result.output
    assert "1 of 1 building meshes pass, 0 fail; 1 MultiSurface meshes not checked" in result.output


def test_validate_meshes_names_the_failing_buildings(tmp_path):
    city = city_of(stepped_box(), split_wall_box())
    write_obj(city, tmp_path / "buildings.obj")
    write_glb(city, tmp_path / "buildings.glb")
    ok = CliRunner().invoke(cli, ["validate", "--meshes", str(tmp_path)])
    assert ok.exit_code == 0, ok.output
    assert "buildings.glb: 2 of 2 building meshes pass" in ok.output
    assert "buildings.obj: 2 of 2 building meshes pass" in ok.output
    text = (tmp_path / "buildings.obj").read_text(encoding="utf-8").splitlines()
    last_face = max(i for i, line in enumerate(text) if line.startswith("f "))
    (tmp_path / "buildings.obj").write_text("\n".join(text[:last_face] + text[last_face + 1 :]) + "\n")
    bad = CliRunner().invoke(cli, ["validate", "--meshes", str(tmp_path)])
    assert bad.exit_code == 1
    assert "buildings.obj: b1: not watertight" in bad.output
    assert "buildings.obj: 1 of 2 building meshes pass, 1 fail (b1)" in bad.output
    assert "buildings.glb: 2 of 2 building meshes pass" in bad.output
    missing = CliRunner().invoke(cli, ["validate", "--meshes", str(tmp_path / "nothing")])
    assert missing.exit_code == 1 and "no buildings.glb or buildings.obj" in missing.output


def test_check_mesh_reports_inside_out():
    mesh = stepped_box().to_trimesh()
    mesh.faces = mesh.faces[:, ::-1]
    check = check_mesh(mesh, "x")
    assert not check.ok and check.volume == pytest.approx(-575.0)
    assert any("inside out" in p for p in check.problems())


# --------------------------------------------------------------------------- real runs


@pytest.mark.parametrize("run_name", RUNS)
def test_run_meshes_closed_and_of_the_cityjson_volume(run_name, request):
    """Every building of the run: GLB and OBJ meshes pass trimesh and manifold3d, volumes as in CityJSON."""
    state = request.getfixturevalue(run_name)
    out = state.out_dir
    city = read_cityjson(out / "buildings.city.json", parts=True)
    expected = {b.id: polygon_volume(b.solids[max(b.solids, key=float)]) for b in city if b.solids}
    assert expected
    for name in ("buildings.glb", "buildings.obj"):
        checks = check_mesh_file(out / name)
        assert sorted(c.id for c in checks) == sorted(expected), name
        failing = [(c.id, c.problems()) for c in checks if not c.ok]
        assert not failing, (name, failing)
        for c in checks:
            assert c.volume == pytest.approx(expected[c.id], rel=1e-3), (name, c.id)
    per_building = trimesh.load(out / "buildings.obj", split_objects=True, group_material=False, process=False)
    assert sorted(per_building.geometry) == sorted(expected)  # one geometry per building
    result = CliRunner().invoke(cli, ["validate", "--meshes", str(out)])
    n = len(expected)
    assert result.exit_code == 0, result.output
    assert f"buildings.glb: {n} of {n} building meshes pass, 0 fail" in result.output
    assert f"buildings.obj: {n} of {n} building meshes pass, 0 fail" in result.output


@pytest.mark.parametrize("name", ["DH_01_subs.city.json", "multi_lod.json"])
def test_other_tools_solids_export_closed(name, tmp_path):
    """Solids written by other tools (Den Haag's BuildingParts, a 3-LoD sample): closed meshes too."""
    city = read_cityjson(shared(f"citymodels/{name}"), parts=True)
    expected = {b.id: polygon_volume(b.solids[max(b.solids, key=float)]) for b in city if b.solids}
    write_glb(city, tmp_path / "b.glb")
    write_obj(city, tmp_path / "b.obj")
    for file in ("b.glb", "b.obj"):
        checks = check_mesh_file(tmp_path / file)
        assert len(checks) == len(expected) and all(c.ok and c.kind == "Solid" for c in checks), checks
        for c in checks:
            assert c.volume == pytest.approx(expected[c.id], rel=1e-3), (file, c.id)


def test_every_solid_of_a_run_meshes_closed(delft_run):
    """Not only the exported highest LoD: every LoD of every building, from the run's own model."""
    for b in delft_run.city:
        for lod, solid in b.solids.items():
            mesh = solid.to_trimesh()
            assert mesh.is_watertight and mesh.is_winding_consistent, (b.id, lod)
            assert manifold_status(mesh.vertices, mesh.faces) == "NoError", (b.id, lod)
            # surfaces up to 1 cm off their plane (val3dity's tolerance): volumes agree to 1e-3
            assert mesh.volume == pytest.approx(polygon_volume(solid), rel=1e-3), (b.id, lod)


def test_a_solid_survives_pickling_with_its_rings_and_mesh():
    """Solids travel to and from the worker processes pickled (rings packed into one array)."""
    import pickle

    from recon3d.buildings.extrude import lod1_solid

    solid = lod1_solid(box(0, 0, 10, 5).difference(box(2, 2, 3, 3)), 0.0, 7.0, LocalFrame((0.0, 0.0, 0.0)))
    mesh = solid.mesh()
    back = pickle.loads(pickle.dumps(solid))
    assert [len(s) for s in back.surfaces] == [len(s) for s in solid.surfaces]  # the courtyard's hole kept
    for ours, theirs in zip(solid.surfaces, back.surfaces, strict=True):
        for a, b in zip(ours, theirs, strict=True):
            assert b.dtype == np.int64 and np.array_equal(a, b)
    assert back.semantics == solid.semantics and back.kind == solid.kind
    np.testing.assert_array_equal(back.vertices, solid.vertices)
    for a, b in zip(mesh, back.mesh(), strict=True):  # the cached triangles travel too
        np.testing.assert_array_equal(a, b)
    assert pickle.loads(pickle.dumps(Solid(np.zeros((0, 3)), [], []))).surfaces == []
