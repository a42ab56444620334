"""glTF export of the buildings of a :class:`~recon3d.core.city.CityModel`: binary or JSON.

:func:`write_glb` writes a binary ``.glb``; :func:`write_gltf` the same scene as one
JSON ``.gltf`` file, its buffer embedded as a base64 data URI (no ``.bin`` beside it).

One node per building, named by its id, holding the building's highest-LoD solid.
glTF specifics handled here:

- **float32**: glTF stores float32 positions, so vertices stay in the model's
  :class:`~recon3d.core.geo.LocalFrame` (millimetres survive); the frame origin
  and CRS go to the scene ``extras`` under ``"recon3d"``.
- **Y up**: glTF is +Y up, recon3d is Z up; positions are rotated
  ``(x, y, z) -> (x, z, -y)`` (a proper rotation, so triangle winding and outward
  normals are kept). Back to the CRS: ``world = (x, -z_gltf, y_gltf) + origin``.
- **Colours**: roofs, walls and ground get the colours of
  :data:`recon3d.io.obj.MATERIALS` as vertex colours (``COLOR_0``, one vertex per
  triangle corner so faces stay flat-coloured) under one matte white PBR material.
- **Attributes**: id, status, reason, heights and ``building.attributes`` are in
  both the node's and the mesh's ``extras``.
"""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np
import trimesh

from recon3d.core.city import CityModel, Solid
from recon3d.core.geo import crs_name
from recon3d.io import atomic_path
from recon3d.io.cityjson import building_attributes
from recon3d.io.obj import MATERIALS, highest_lod

log = logging.getLogger(__name__)

__all__ = ["GLTF_FROM_LOCAL", "write_glb", "write_gltf"]

#: (3, 3) rotation taking local Z-up (x, y, z) to glTF Y-up (x, z, -y): ``p_gltf = R @ p``.
GLTF_FROM_LOCAL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

_GREY = (0.6, 0.6, 0.6)


def write_glb(city: CityModel, path: str | Path) -> None:
    """Write the buildings with a solid as a GLB file (atomic).

    Buildings without any solid are skipped (they are listed in the CityJSON file).
    """
    scene = build_scene(city)
    if scene.geometry:
        data = scene.export(file_type="glb")
    else:  # trimesh refuses empty scenes; a glTF without nodes is still valid
        log.warning("no building has a solid: %s holds an empty scene", path)
        data = _empty_glb(scene.metadata)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    log.info("wrote %d building nodes to %s", len(scene.geometry), path)


def write_gltf(city: CityModel, path: str | Path) -> None:
    """Write the scene of :func:`write_glb` as one JSON glTF file, its buffer embedded (atomic)."""
    scene = build_scene(city)
    if scene.geometry:
        data = scene.export(file_type="gltf", embed_buffers=True)["model.gltf"]
    else:
        log.warning("no building has a solid: %s holds an empty scene", path)
        data = json.dumps(_empty_document(scene.metadata), separators=(",", ":")).encode("utf-8")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    log.info("wrote %d building nodes to %s", len(scene.geometry), path)


def _empty_document(extras: dict) -> dict:
    """A glTF document with one empty scene carrying ``extras``."""
    return {
        "asset": {"version": "2.0", "generator": "recon3d"},
        "scene": 0,
        "scenes": [{"nodes": [], "extras": extras}],
    }


def _empty_glb(extras: dict) -> bytes:
    """A GLB with one empty scene carrying ``extras`` (header + JSON chunk, no buffer)."""
    chunk = json.dumps(_empty_document(extras), separators=(",", ":")).encode("utf-8")
    chunk += b" " * (-len(chunk) % 4)  # chunks are 4-byte aligned, JSON padded with spaces
    header = struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(chunk))
    return header + struct.pack("<II", len(chunk), 0x4E4F534A) + chunk


def build_scene(city: CityModel) -> trimesh.Scene:
    """The :class:`trimesh.Scene` :func:`write_glb` exports (one node per building)."""
    scene = trimesh.Scene()
    for building in city.buildings:
        lod = highest_lod(building)
        if lod is None:
            continue
        mesh = _building_mesh(building.solids[lod])
        extras = {"id": str(building.id), "lod": lod, **building_attributes(building)}
        if building.parent is not None:
            extras["parent"] = building.parent  # the block this part belongs to
        mesh.metadata.update(extras)
        name = str(building.id)
        scene.add_geometry(mesh, node_name=name, geom_name=name, metadata=extras)
    scene.metadata["recon3d"] = {
        "origin": [float(v) for v in city.frame.origin],
        "crs": crs_name(city.crs),
        "up": "Y",
        "units": "CRS units",
        "note": "world = local(x, -z_gltf, y_gltf) + origin",
    }
    return scene


def _building_mesh(solid: Solid) -> trimesh.Trimesh:
    """Triangulated solid in glTF axes, one vertex per triangle corner, coloured by semantics.

    Returns
    -------
    trimesh.Trimesh
        (3 m, 3) float64 vertices and (m, 3) faces for m triangles, with a
        ``COLOR_0`` vertex attribute (uint8 RGBA) and a matte PBR material.
    """
    tri = solid.to_trimesh()
    corners = tri.vertices[tri.faces.reshape(-1)] @ GLTF_FROM_LOCAL.T
    faces = np.arange(len(corners), dtype=np.int64).reshape(-1, 3)
    rgb = np.array([MATERIALS.get(k, (None, _GREY))[1] for k in solid.semantics] or [_GREY])
    face_rgb = rgb[tri.metadata["surface_index"]]
    rgba = np.column_stack([np.rint(face_rgb * 255), np.full(len(face_rgb), 255)]).astype(np.uint8)
    material = trimesh.visual.material.PBRMaterial(
        name="building",
        baseColorFactor=[255, 255, 255, 255],
        metallicFactor=0.0,
        roughnessFactor=1.0,
    )
    mesh = trimesh.Trimesh(corners, faces, process=False)
    mesh.visual = trimesh.visual.TextureVisuals(material=material)
    mesh.visual.vertex_attributes["color"] = np.repeat(rgba, 3, axis=0)
    return mesh
