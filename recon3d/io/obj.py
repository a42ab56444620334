"""Wavefront OBJ + MTL export of the buildings of a :class:`~recon3d.core.city.CityModel`.

One object (``o <id>``) per building: its highest-LoD solid as the triangles of
:meth:`~recon3d.core.city.Solid.mesh` (shared vertices, no T-junctions, so each
building is a closed shell), with one material of its own (``usemtl <id>``, defined in
the MTL file beside the OBJ), so that Blender (by object) and trimesh's default load
(by material) both give one mesh per building. Inside the object, one group per
semantic surface type (``g <id>_ground``, ``_wall``, ``_roof``: trimesh's
``split_groups=True`` or Blender's "Split by Group" gives the surfaces apart). Each
building's material is the matte wall colour of the GLB; roofs and walls are not
coloured apart, because a material per surface type makes trimesh merge every
building's roofs into one mesh, and vertex colours would blend at the eaves (a
vertex shared by a wall and a roof has one colour). A building whose
surfaces close no volume (a MultiSurface read from another tool) has the comment
:data:`SURFACES_COMMENT` after its ``usemtl`` line. Coordinates stay in the model's local frame and in CRS
units, Z up (OBJ has no georeferencing; the header comment gives the CRS and the
origin: ``world = local + origin``). Six decimals keep well under a millimetre.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np

from recon3d.core.city import SEMANTIC_TYPES, Building, CityModel, Solid
from recon3d.core.geo import crs_name, uncoded_wkt
from recon3d.io import atomic_path

log = logging.getLogger(__name__)

__all__ = ["MATERIALS", "SURFACES_COMMENT", "highest_lod", "semantic_material", "surface_order", "write_obj"]

#: Group suffix and RGB colour (0-1) per CityJSON semantic surface type (3D Tiles
#: colours every surface type; OBJ and GLB use the wall colour for the building).
MATERIALS: dict[str, tuple[str, tuple[float, float, float]]] = {
    "RoofSurface": ("roof", (0.78, 0.27, 0.20)),
    "WallSurface": ("wall", (0.90, 0.87, 0.80)),
    "GroundSurface": ("ground", (0.35, 0.35, 0.35)),
}
#: Material of any other surface type (ClosureSurface...).
_DEFAULT_TYPE = "WallSurface"
#: Comment line marking an object as surfaces, not a closed solid (``Solid.kind == "MultiSurface"``).
SURFACES_COMMENT = "# MultiSurface: surfaces, not a closed solid"


def highest_lod(building: Building) -> str | None:
    """The building's highest LoD key ("2.2" over "1"), or None without solids."""
    return max(building.solids, key=float) if building.solids else None


def semantic_material(kind: str) -> str:
    """Group suffix ("roof", "wall", "ground") of a semantic surface type."""
    return MATERIALS.get(kind, MATERIALS[_DEFAULT_TYPE])[0]


def surface_order(solid: Solid, surface: np.ndarray) -> tuple[np.ndarray, dict[str, list[int]]]:
    """Triangles ordered by semantic type: ground, walls, roofs, then any other type.

    Parameters
    ----------
    solid : Solid
    surface : (m,) int
        Surface of each triangle (``Solid.mesh().surface``).

    Returns
    -------
    order : (m,) int64
        Stable permutation of the triangles.
    ranges : dict of str to [int, int]
        First (in the new order) and count of the triangles of each type present.
    """
    kinds = np.array(solid.semantics, dtype=object)[surface] if len(surface) else np.zeros(0, object)
    types = list(SEMANTIC_TYPES)  # ground, wall, roof
    types += sorted(set(kinds.tolist()) - set(types))
    rank = np.array([types.index(k) for k in kinds], dtype=np.int64)
    order = np.argsort(rank, kind="stable")
    count = np.bincount(rank, minlength=len(types))
    first = np.r_[0, np.cumsum(count)[:-1]]
    ranges = {t: [int(f), int(c)] for t, f, c in zip(types, first, count, strict=True) if c}
    return order, ranges


def write_obj(city: CityModel, path: str | Path) -> None:
    """Write the buildings as an OBJ file and its MTL (same stem, ``.mtl``), atomically.

    Buildings without a solid are skipped (they are listed in the CityJSON file).
    """
    path = Path(path)
    mtl_path = path.with_suffix(".mtl")
    with atomic_path(path) as tmp_obj, atomic_path(mtl_path) as tmp_mtl:
        tmp_mtl.write_text(_mtl_text(_names(city)), encoding="utf-8")
        tmp_obj.write_text(_obj_text(city, mtl_path.name), encoding="utf-8")
    log.info("wrote %s and %s", path, mtl_path.name)


def _names(city: CityModel) -> list[str]:
    """Object and material name of each building written (those with a solid)."""
    return [_name(b) for b in city.buildings if b.solids]


def _name(building: Building) -> str:
    """The building's id without whitespace (OBJ names end at the first blank)."""
    return "_".join(str(building.id).split()) or "building"


def _mtl_text(names: list[str]) -> str:
    """MTL with one matte material per building, in the wall colour."""
    r, g, b = MATERIALS["WallSurface"][1]
    colour = f"Ka {r:.3f} {g:.3f} {b:.3f}\nKd {r:.3f} {g:.3f} {b:.3f}\nKs 0.000 0.000 0.000\nd 1.0\nillum 1\n"
    return "# recon3d building materials: one per building\n\n" + "\n".join(
        f"newmtl {name}\n{colour}" for name in dict.fromkeys(names))


def _obj_text(city: CityModel, mtl_name: str) -> str:
    """The OBJ file: header, ``mtllib``, then one object per building."""
    x0, y0, z0 = city.frame.origin
    out = io.StringIO()
    out.write(
        "# recon3d buildings\n"
        f"# CRS: {crs_name(city.crs)}\n"
        + (f"# CRS WKT: {wkt}\n" if (wkt := uncoded_wkt(city.crs)) else "")
        + f"# origin: {x0:.6f} {y0:.6f} {z0:.6f}\n"
        "# coordinates are local, in CRS units, Z up: world = local + origin\n"
        f"mtllib {mtl_name}\n"
    )
    offset = 1  # OBJ vertex indices are 1-based and global to the file
    for building in city.buildings:
        lod = highest_lod(building)
        if lod is None:
            continue
        offset += _write_building(out, building, building.solids[lod], offset)
    return out.getvalue()


def _write_building(out: io.StringIO, building: Building, solid: Solid, offset: int) -> int:
    """Append one building (vertices, then faces grouped by surface type); return its vertex count."""
    vertices, faces, surface = solid.mesh()
    name = _name(building)
    out.write(f"o {name}\nusemtl {name}\n")
    if solid.kind != "Solid":
        out.write(SURFACES_COMMENT + "\n")
    _write_rows(out, "v %.6f %.6f %.6f", vertices)
    order, ranges = surface_order(solid, surface)
    faces = faces[order] + offset
    for kind, (first, count) in ranges.items():
        out.write(f"g {name}_{semantic_material(kind)}\n")
        _write_rows(out, "f %d %d %d", faces[first : first + count])
    return len(vertices)


def _write_rows(out: io.StringIO, fmt: str, rows: np.ndarray) -> None:
    """One line ``fmt % row`` per row of a (n, 3) array (what ``np.savetxt`` writes, in one join)."""
    line = fmt + "\n"
    out.write("".join([line % tuple(row) for row in rows.tolist()]))
