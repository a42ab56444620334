"""Wavefront OBJ + MTL export of the buildings of a :class:`~recon3d.core.city.CityModel`.

One object (``o <id>`` and ``g <id>``) per building, its highest-LoD solid
triangulated, with a material per semantic surface type (roof, wall, ground) in an
MTL file beside the OBJ. Coordinates stay in the model's local frame and in CRS
units, Z up (OBJ has no georeferencing; the header comment gives the CRS and the
origin: ``world = local + origin``). Six decimals keep well under a millimetre.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np

from recon3d.core.city import Building, CityModel, Solid
from recon3d.core.geo import crs_name, uncoded_wkt
from recon3d.io import atomic_path

log = logging.getLogger(__name__)

__all__ = ["MATERIALS", "highest_lod", "semantic_material", "write_obj"]

#: Material name and diffuse RGB colour (0-1) per CityJSON semantic surface type.
MATERIALS: dict[str, tuple[str, tuple[float, float, float]]] = {
    "RoofSurface": ("roof", (0.78, 0.27, 0.20)),
    "WallSurface": ("wall", (0.90, 0.87, 0.80)),
    "GroundSurface": ("ground", (0.35, 0.35, 0.35)),
}
#: Material of any other surface type (ClosureSurface...).
_DEFAULT_TYPE = "WallSurface"


def highest_lod(building: Building) -> str | None:
    """The building's highest LoD key ("2.2" over "1"), or None without solids."""
    return max(building.solids, key=float) if building.solids else None


def semantic_material(kind: str) -> str:
    """Material name ("roof", "wall", "ground") of a semantic surface type."""
    return MATERIALS.get(kind, MATERIALS[_DEFAULT_TYPE])[0]


def write_obj(city: CityModel, path: str | Path) -> None:
    """Write the buildings as an OBJ file and its MTL (same stem, ``.mtl``), atomically.

    Buildings without a solid are skipped (they are listed in the CityJSON file).
    """
    path = Path(path)
    mtl_path = path.with_suffix(".mtl")
    with atomic_path(path) as tmp_obj, atomic_path(mtl_path) as tmp_mtl:
        tmp_mtl.write_text(_mtl_text(), encoding="utf-8")
        tmp_obj.write_text(_obj_text(city, mtl_path.name), encoding="utf-8")
    log.info("wrote %s and %s", path, mtl_path.name)


def _mtl_text() -> str:
    """MTL with one matte material per semantic type."""
    blocks = [
        f"newmtl {name}\nKa {r:.3f} {g:.3f} {b:.3f}\nKd {r:.3f} {g:.3f} {b:.3f}\n"
        "Ks 0.000 0.000 0.000\nd 1.0\nillum 1\n"
        for name, (r, g, b) in MATERIALS.values()
    ]
    return "# recon3d building materials\n\n" + "\n".join(blocks)


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
    """Append one building (vertices, then faces grouped by material); return its vertex count."""
    mesh = solid.to_trimesh()
    name = "_".join(str(building.id).split()) or "building"
    out.write(f"o {name}\ng {name}\n")
    np.savetxt(out, mesh.vertices, fmt="v %.6f %.6f %.6f")
    per_surface = np.array([semantic_material(k) for k in solid.semantics] or [""])
    materials = per_surface[mesh.metadata["surface_index"]]
    for material in dict.fromkeys(materials.tolist()):
        out.write(f"usemtl {material}\n")
        np.savetxt(out, mesh.faces[materials == material] + offset, fmt="f %d %d %d")
    return len(mesh.vertices)
