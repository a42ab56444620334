"""glTF export of the buildings of a :class:`~recon3d.core.city.CityModel`: binary or JSON.

:func:`write_glb` writes a binary ``.glb``; :func:`write_gltf` the same scene as one
JSON ``.gltf`` file, its buffer embedded as a base64 data URI (no ``.bin`` beside it).

One node per building, named by its id, holding the building's highest-LoD solid as
one mesh of one primitive: the triangles of :meth:`~recon3d.core.city.Solid.mesh`,
on shared vertices and without T-junctions, so that trimesh, Blender and manifold3d
load each building as one closed, outward-facing shell. glTF specifics handled here:

- **float32**: glTF stores float32 positions, so vertices stay in the model's
  :class:`~recon3d.core.geo.LocalFrame` (millimetres survive); the frame origin
  and CRS go to the scene ``extras`` under ``"recon3d"``.
- **Y up**: glTF is +Y up, recon3d is Z up; positions are rotated
  ``(x, y, z) -> (x, z, -y)`` (a proper rotation, so triangle winding and outward
  normals are kept). Back to the CRS: ``world = (x, -z_gltf, y_gltf) + origin``.
- **Semantics**: the triangles are ordered by surface type (ground, walls, roofs)
  and the mesh's ``extras["surface_types"]`` gives, per CityJSON type, the first
  triangle and the count: ``{"RoofSurface": [first, count], ...}``. A vertex shared
  by a wall and a roof has one colour in glTF, so surfaces are not coloured by
  type (that would split the shell at every eave); one matte material, and no
  normals, so viewers shade every face flat.
- **Attributes**: id, status, reason, heights, ``geometry_type`` ("Solid", or
  "MultiSurface" for surfaces read from another tool that close no volume) and
  ``building.attributes`` are in both the node's and the mesh's ``extras``.

:func:`write_textured_glb` writes the same buildings for looking at: roofs and walls
textured from the stereo images (:mod:`recon3d.stereo.texture`), one primitive per
texture a building uses, the images embedded as JPEG. A corner shared by a roof and a
wall has two texture coordinates, so there each primitive keeps its own copy of it:
the shell is closed by position, not by shared vertices (weld by position, as
trimesh's ``merge_vertices`` does, to get the solid back).
"""

from __future__ import annotations

import base64
import json
import logging
import struct
from pathlib import Path

import numpy as np

from recon3d.core.city import CityModel
from recon3d.core.geo import crs_name, uncoded_wkt
from recon3d.io import atomic_path
from recon3d.io.glb import Binary, accessor, glb, index_accessor
from recon3d.io.cityjson import building_attributes
from recon3d.io.obj import MATERIALS, highest_lod, surface_order

log = logging.getLogger(__name__)

__all__ = ["GLTF_FROM_LOCAL", "JPEG_QUALITY", "write_glb", "write_gltf", "write_textured_glb"]

#: (3, 3) rotation taking local Z-up (x, y, z) to glTF Y-up (x, z, -y): ``p_gltf = R @ p``.
GLTF_FROM_LOCAL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: Base colour (RGBA, 0-1) of the one material: the walls' colour.
_COLOUR = [*MATERIALS["WallSurface"][1], 1.0]

#: JPEG quality of the textures of :func:`write_textured_glb`.
JPEG_QUALITY = 90

#: glTF sampler: bilinear, mipmapped, clamped (texture coordinates stay within [0, 1]).
_SAMPLER = {"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}


def write_glb(city: CityModel, path: str | Path) -> None:
    """Write the buildings with a solid as a GLB file (atomic).

    Buildings without any solid are skipped (they are listed in the CityJSON file).
    """
    doc, data = plain_document(city)
    with atomic_path(path) as tmp:
        tmp.write_bytes(glb(doc, data) if doc["nodes"] else _empty_glb(doc["scenes"][0]["extras"]))
    _log_written(doc, path)


def write_gltf(city: CityModel, path: str | Path) -> None:
    """Write the scene of :func:`write_glb` as one JSON glTF file, its buffer embedded (atomic)."""
    doc, data = plain_document(city)
    if doc["nodes"]:
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")
    else:
        doc = _empty_document(doc["scenes"][0]["extras"])
    with atomic_path(path) as tmp:
        tmp.write_bytes(json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode("utf-8"))
    _log_written(doc, path)


def _log_written(doc: dict, path) -> None:
    if not doc.get("nodes"):
        log.warning("no building has a solid: %s holds an empty scene", path)
    log.info("wrote %d building nodes to %s", len(doc.get("nodes", [])), path)


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


def plain_document(city: CityModel) -> tuple[dict, bytes]:
    """The glTF document :func:`write_glb` writes (one node per building with a solid,
    one matte material) and its binary buffer.

    Returns
    -------
    doc : dict
        The glTF JSON; ``buffers[0]`` has no ``uri`` (the GLB's own chunk).
    data : bytes
        The buffer: per building, float32 (n, 3) positions then uint32 (m, 3) triangles.
    """
    binary = Binary()
    accessors, meshes, nodes = [], [], []
    for building in city.buildings:
        lod = highest_lod(building)
        if lod is None:
            continue
        vertices, faces, surface = building.solids[lod].mesh()
        order, ranges = surface_order(building.solids[lod], surface)
        extras = _building_extras(building, lod)
        accessors.append(accessor((vertices @ GLTF_FROM_LOCAL.T).astype(np.float32), binary, "VEC3", bounds=True))
        accessors.append(index_accessor(faces[order], binary))
        primitive = {"attributes": {"POSITION": len(accessors) - 2}, "indices": len(accessors) - 1, "mode": 4,
                     "material": 0}
        nodes.append({"name": str(building.id), "mesh": len(meshes), "extras": extras})
        meshes.append({"name": str(building.id), "primitives": [primitive], "extras": {**extras, "surface_types": ranges}})
    data = binary.padded()
    doc = {
        "asset": {"version": "2.0", "generator": "recon3d"},
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes))), "extras": build_scene_extras(city)}],
        "nodes": nodes, "meshes": meshes, "accessors": accessors,
        "materials": [{"name": "building", "pbrMetallicRoughness": {
            "baseColorFactor": _COLOUR, "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "bufferViews": binary.views, "buffers": [{"byteLength": len(data)}],
    }
    return doc, data


def build_scene_extras(city: CityModel) -> dict:
    """The scene's ``extras``: ``{"recon3d": {origin, crs, up, units, note}}``, the way back to the CRS."""
    info = {
        "origin": [float(v) for v in city.frame.origin],
        "crs": crs_name(city.crs),
        "up": "Y",
        "units": "CRS units",
        "note": "world = local(x, -z_gltf, y_gltf) + origin",
    }
    if uncoded_wkt(city.crs):  # a CRS without an EPSG code travels as its WKT
        info["crs_wkt"] = uncoded_wkt(city.crs)
    return {"recon3d": info}


def write_textured_glb(city: CityModel, model, path: str | Path) -> None:
    """Write the buildings of ``model`` (:class:`~recon3d.stereo.texture.TexturedModel`)
    as a textured GLB file (atomic): one node per building, named and with ``extras``
    as in :func:`write_glb`, one primitive per texture it uses."""
    binary = Binary()
    images, materials = _textured_materials(model.textures, binary, path)
    plain = len(materials) - 1  # untextured surfaces: the walls' colour, as in write_glb
    accessors, meshes = [], []
    for building in city.buildings:
        parts = model.parts.get(str(building.id))
        if parts:
            primitives = [_primitive(part, binary, accessors, plain) for part in parts]
            meshes.append({"name": str(building.id), "primitives": primitives,
                           "extras": _building_extras(building, highest_lod(building))})
    nodes = [{"name": m["name"], "mesh": i, "extras": m["extras"]} for i, m in enumerate(meshes)]
    scene_extras = build_scene_extras(city)
    data = binary.padded()
    doc = {
        "asset": {"version": "2.0", "generator": "recon3d"},
        "scene": 0,
        "scenes": [{"nodes": list(range(len(nodes))), "extras": scene_extras}],
        "nodes": nodes, "meshes": meshes, "materials": materials, "accessors": accessors,
        "bufferViews": binary.views, "buffers": [{"byteLength": len(data)}],
    }
    if images:
        doc.update(images=images, samplers=[_SAMPLER], textures=[{"sampler": 0, "source": i} for i in range(len(images))])
    if not nodes:
        log.warning("no building has a solid: %s holds an empty scene", path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(glb(doc, data) if nodes else _empty_glb(scene_extras))
    log.info("wrote %d textured building nodes (%d textures) to %s", len(nodes), len(images), path)


def _building_extras(building, lod: str) -> dict:
    """A building's node and mesh ``extras``: id, LoD, geometry type, attributes and block."""
    extras = {"id": str(building.id), "lod": lod, "geometry_type": building.solids[lod].kind,
              **building_attributes(building)}
    if building.parent is not None:
        extras["parent"] = building.parent  # the block this part belongs to
    return extras


def _textured_materials(textures: list, binary: Binary, path) -> tuple[list[dict], list[dict]]:
    """The images (JPEG in ``binary``) and one material per texture, then the plain one."""
    import cv2

    images = []
    for texture in textures:
        ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(texture.image, cv2.COLOR_RGB2BGR),
                                [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise ValueError(f"{path}: texture {texture.name!r} could not be encoded as JPEG")
        images.append({"name": texture.name, "bufferView": binary.view(jpeg.tobytes()), "mimeType": "image/jpeg"})
    matte = {"metallicFactor": 0.0, "roughnessFactor": 1.0}
    materials = [{"name": t.name, "pbrMetallicRoughness": {"baseColorTexture": {"index": i}, **matte}}
                 for i, t in enumerate(textures)]
    materials.append({"name": "building", "pbrMetallicRoughness": {"baseColorFactor": _COLOUR, **matte}})
    return images, materials


def _primitive(part, binary: Binary, accessors: list[dict], plain: int) -> dict:
    """The glTF primitive of one :class:`~recon3d.stereo.texture.Part`, its accessors appended."""
    attributes = {"POSITION": len(accessors)}
    accessors.append(accessor((part.vertices @ GLTF_FROM_LOCAL.T).astype(np.float32), binary, "VEC3", bounds=True))
    if part.texture >= 0:
        attributes["TEXCOORD_0"] = len(accessors)
        accessors.append(accessor(part.uv.astype(np.float32), binary, "VEC2"))
    accessors.append(index_accessor(part.faces, binary))
    return {"attributes": attributes, "indices": len(accessors) - 1, "mode": 4,
            "material": part.texture if part.texture >= 0 else plain}
