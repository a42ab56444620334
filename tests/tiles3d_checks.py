"""Checks of a 3D Tiles 1.1 tileset folder, for the tests.

- :data:`TILESET_SCHEMA`: the structure of tileset.json as the 3D Tiles 1.1
  specification defines it (asset, tile, boundingVolume, content), closed to unknown
  properties, as a JSON Schema (2020-12) for the ``jsonschema`` package. The official
  schema files are used instead when ``../shared/data/schemas/3d-tiles-1.1`` holds them.
- :func:`check_tileset`: the rules the 3d-tiles-validator applies beyond the schema
  (a child's geometric error at most its parent's, an affine transform, every content
  inside its tile's box and every ancestor's), the GLB container and accessors of each
  content (what pygltflib would check: header, chunk lengths and alignment, buffer
  views inside the buffer, POSITION min/max equal to the data) and the
  ``EXT_mesh_features`` / ``EXT_structural_metadata`` tables (feature ids below the
  feature count, property table columns of the right length).
"""

from __future__ import annotations

import itertools
import json
import struct
from pathlib import Path

import numpy as np

_NUMBERS = {"type": "array", "items": {"type": "number"}}

TILESET_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "required": ["asset", "geometricError", "root"],
    "properties": {
        "asset": {"$ref": "#/$defs/asset"},
        "geometricError": {"type": "number", "minimum": 0},
        "root": {"$ref": "#/$defs/tile"},
        "properties": {"type": "object"},
        "schema": {"type": "object"},
        "schemaUri": {"type": "string"},
        "statistics": {"type": "object"},
        "groups": {"type": "array"},
        "metadata": {"type": "object"},
        "extensionsUsed": {"type": "array", "items": {"type": "string"}, "uniqueItems": True, "minItems": 1},
        "extensionsRequired": {"type": "array", "items": {"type": "string"}, "uniqueItems": True, "minItems": 1},
        "extensions": {"type": "object"},
        "extras": {},
    },
    "additionalProperties": False,
    "$defs": {
        "asset": {
            "type": "object",
            "required": ["version"],
            "properties": {"version": {"const": "1.1"}, "tilesetVersion": {"type": "string"},
                           "extensions": {"type": "object"}, "extras": {}},
            "additionalProperties": False,
        },
        "boundingVolume": {
            "type": "object",
            "minProperties": 1,
            "properties": {
                "box": {**_NUMBERS, "minItems": 12, "maxItems": 12},
                "region": {**_NUMBERS, "minItems": 6, "maxItems": 6},
                "sphere": {**_NUMBERS, "minItems": 4, "maxItems": 4},
                "extensions": {"type": "object"}, "extras": {},
            },
            "additionalProperties": False,
        },
        "content": {
            "type": "object",
            "required": ["uri"],
            "properties": {"uri": {"type": "string"}, "boundingVolume": {"$ref": "#/$defs/boundingVolume"},
                           "metadata": {"type": "object"}, "group": {"type": "integer", "minimum": 0},
                           "extensions": {"type": "object"}, "extras": {}},
            "additionalProperties": False,
        },
        "tile": {
            "type": "object",
            "required": ["boundingVolume", "geometricError"],
            "properties": {
                "boundingVolume": {"$ref": "#/$defs/boundingVolume"},
                "viewerRequestVolume": {"$ref": "#/$defs/boundingVolume"},
                "geometricError": {"type": "number", "minimum": 0},
                "refine": {"enum": ["ADD", "REPLACE"]},
                "transform": {**_NUMBERS, "minItems": 16, "maxItems": 16},
                "content": {"$ref": "#/$defs/content"},
                "contents": {"type": "array", "items": {"$ref": "#/$defs/content"}},
                "metadata": {"type": "object"},
                "implicitTiling": {"type": "object"},
                "children": {"type": "array", "items": {"$ref": "#/$defs/tile"}, "minItems": 1, "uniqueItems": True},
                "extensions": {"type": "object"}, "extras": {},
            },
            "not": {"required": ["content", "contents"]},
            "additionalProperties": False,
        },
    },
}

#: (3, 3) glTF y-up to 3D Tiles z-up: ``p_tile = Y_UP_TO_Z_UP @ p_gltf`` (x, -z, y).
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

_COMPONENTS = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


# --------------------------------------------------------------------------- GLB


def read_glb(path: Path) -> tuple[dict, bytes]:
    """The JSON and BIN chunks of a GLB, after checking its container."""
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data)), path
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0, path
    doc = json.loads(data[20 : 20 + json_len])
    at = 20 + json_len
    bin_len, bin_type = struct.unpack_from("<II", data, at)
    assert bin_type == 0x004E4942 and bin_len % 4 == 0 and at + 8 + bin_len == len(data), path
    binary = data[at + 8 :]
    assert doc["asset"]["version"] == "2.0" and doc["buffers"][0]["byteLength"] <= bin_len
    return doc, binary


def view_bytes(doc: dict, binary: bytes, index: int) -> bytes:
    """The bytes of buffer view ``index`` (checked to lie in the buffer)."""
    view = doc["bufferViews"][index]
    start, size = view.get("byteOffset", 0), view["byteLength"]
    assert size > 0 and start + size <= doc["buffers"][0]["byteLength"]
    return binary[start : start + size]


def accessor(doc: dict, binary: bytes, index: int) -> np.ndarray:
    """(count, k) or (count,) data of an accessor; its min/max, when given, are the data's."""
    acc = doc["accessors"][index]
    raw = view_bytes(doc, binary, acc["bufferView"])
    dtype = np.dtype(_COMPONENTS[acc["componentType"]])
    width = _WIDTH[acc["type"]]
    assert acc.get("byteOffset", 0) + acc["count"] * width * dtype.itemsize <= len(raw)
    values = np.frombuffer(raw, dtype, acc["count"] * width, acc.get("byteOffset", 0))
    values = values.reshape(acc["count"], width) if width > 1 else values
    if "min" in acc:
        assert np.array_equal(np.asarray(acc["min"], dtype), values.min(axis=0).reshape(-1)), "accessor min"
        assert np.array_equal(np.asarray(acc["max"], dtype), values.max(axis=0).reshape(-1)), "accessor max"
    return values


def content_vertices(doc: dict, binary: bytes) -> np.ndarray:
    """(n, 3) float64 vertices of every primitive in the tile's z-up frame (node translations)."""
    out = []
    for node in doc["nodes"]:
        offset = np.asarray(node.get("translation", [0, 0, 0]), dtype=np.float64)
        assert "matrix" not in node and "rotation" not in node and "scale" not in node
        for prim in doc["meshes"][node["mesh"]]["primitives"]:
            pos = accessor(doc, binary, prim["attributes"]["POSITION"]).astype(np.float64)
            out.append((pos + offset) @ Y_UP_TO_Z_UP.T)
    return np.concatenate(out)


def feature_table(doc: dict, binary: bytes) -> list[dict]:
    """The property table of the content as one dict per feature (after checking its columns)."""
    meta = doc["extensions"]["EXT_structural_metadata"]
    table = meta["propertyTables"][0]
    props = meta["schema"]["classes"][table["class"]]["properties"]
    count = table["count"]
    rows = [{} for _ in range(count)]
    for ident, column in table["properties"].items():
        for i, value in enumerate(_column_values(doc, binary, props[ident], column, count)):
            if value != props[ident].get("noData", object()):
                rows[i][props[ident]["name"]] = value
    for ident, prop in props.items():
        if prop.get("required"):
            assert ident in table["properties"], ident
    return rows


def _column_values(doc: dict, binary: bytes, prop: dict, column: dict, count: int) -> list:
    values = view_bytes(doc, binary, column["values"])
    if prop["type"] == "SCALAR":
        assert prop["componentType"] == "FLOAT64" and len(values) == 8 * count
        return np.frombuffer(values, "<f8").tolist()
    if prop["type"] == "BOOLEAN":
        assert len(values) == (count + 7) // 8
        return np.unpackbits(np.frombuffer(values, np.uint8), bitorder="little")[:count].astype(bool).tolist()
    assert prop["type"] == "STRING"
    offsets = np.frombuffer(view_bytes(doc, binary, column["stringOffsets"]), "<u4")
    assert len(offsets) == count + 1 and offsets[0] == 0 and np.all(np.diff(offsets.astype(np.int64)) >= 0)
    assert offsets[-1] <= len(values)
    return [values[a:b].decode("utf-8") for a, b in itertools.pairwise(offsets)]


def check_features(doc: dict, binary: bytes) -> np.ndarray:
    """(v,) feature id of each vertex, after checking them against the feature count."""
    (prim,) = doc["meshes"][0]["primitives"]
    (ids,) = prim["extensions"]["EXT_mesh_features"]["featureIds"]
    acc = doc["accessors"][prim["attributes"][f"_FEATURE_ID_{ids['attribute']}"]]
    assert acc["type"] == "SCALAR" and not acc.get("normalized", False)
    feature = accessor(doc, binary, prim["attributes"][f"_FEATURE_ID_{ids['attribute']}"])
    table = doc["extensions"]["EXT_structural_metadata"]["propertyTables"][ids["propertyTable"]]
    assert ids["featureCount"] == table["count"]
    assert feature.min() >= 0 and feature.max() < ids["featureCount"]
    assert np.all(feature == np.round(feature))  # float ids are whole numbers
    assert set(doc["extensionsUsed"]) >= {"EXT_mesh_features", "EXT_structural_metadata"}
    return feature.astype(np.int64)


# --------------------------------------------------------------------------- tileset


def tiles(tile: dict, ancestors: tuple = ()):
    """Yield (tile, its ancestors) for every tile, depth first."""
    yield tile, ancestors
    for child in tile.get("children", []):
        yield from tiles(child, (*ancestors, tile))


def inside_box(points: np.ndarray, box: list[float], eps: float = 1e-5) -> bool:
    """Whether (n, 3) points lie in a 3D Tiles ``box`` (centre and three half axes)."""
    b = np.asarray(box, dtype=np.float64)
    centre, axes = b[:3], b[3:].reshape(3, 3)
    lengths = np.linalg.norm(axes, axis=1)
    local = (points - centre) @ (axes / lengths[:, None]).T
    return bool(np.all(np.abs(local) <= lengths + eps))


def check_tileset(folder: Path) -> dict:
    """Check a tileset folder; returns {"tileset", "contents": {uri: (glTF, bin)}}."""
    import jsonschema

    doc = json.loads((folder / "tileset.json").read_text(encoding="utf-8"))
    errors = list(jsonschema.Draft202012Validator(TILESET_SCHEMA).iter_errors(doc))
    assert not errors, errors[0]
    root = doc["root"]
    assert root["geometricError"] <= doc["geometricError"] and root["refine"] in ("ADD", "REPLACE")
    transform = np.asarray(root["transform"]).reshape(4, 4).T
    assert np.allclose(transform[3], [0, 0, 0, 1], atol=1e-8)
    contents = {}
    for tile, ancestors in tiles(root):
        assert "transform" not in tile or tile is root  # one frame for the whole tileset
        if ancestors:
            assert tile["geometricError"] <= ancestors[-1]["geometricError"]
        if "content" in tile:
            uri = tile["content"]["uri"]
            assert uri not in contents and (folder / uri).is_file(), uri
            gltf, binary = read_glb(folder / uri)
            check_features(gltf, binary)
            vertices = content_vertices(gltf, binary)
            for t in (tile, *ancestors):
                assert inside_box(vertices, t["boundingVolume"]["box"]), uri
            contents[uri] = (gltf, binary)
    on_disk = {p.relative_to(folder).as_posix() for p in folder.rglob("*.glb")}
    assert on_disk == set(contents)  # no stray content
    return {"tileset": doc, "contents": contents}
