"""The GLB container, written by hand: its binary chunk, accessors and header.

Shared by the 3D Tiles content (:mod:`recon3d.io.tiles3d`) and the building models
(:mod:`recon3d.io.gltf`): trimesh cannot write some of these documents (metadata
extensions; several textured primitives per building sharing images), and importing
it to write the others costs a run about a second of its last, single-core stage.
"""

from __future__ import annotations

import json
import struct

import numpy as np

__all__ = ["ARRAY_BUFFER", "ELEMENT_ARRAY_BUFFER", "Binary", "accessor", "glb", "index_accessor"]

#: glTF component types and buffer view targets.
FLOAT, UBYTE, UINT = 5126, 5121, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


class Binary:
    """The binary chunk of a GLB being assembled, and its buffer views."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []

    def view(self, payload: bytes, target: int | None = None) -> int:
        """Append ``payload`` (8-byte aligned, as property tables want); its view's index.

        An empty payload (the strings of a column of empty strings) takes one byte: a
        buffer view is never empty.
        """
        payload = payload or b"\0"
        self.data += b"\0" * (-len(self.data) % 8)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(payload)}
        if target is not None:
            view["target"] = target
        self.data += payload
        self.views.append(view)
        return len(self.views) - 1

    def padded(self) -> bytes:
        """The chunk's bytes, padded to 4 bytes as GLB requires."""
        return bytes(self.data) + b"\0" * (-len(self.data) % 4)


def accessor(data: np.ndarray, binary: Binary, kind: str, *, bounds: bool = False, normalized: bool = False) -> dict:
    """An accessor over (n, k) or (n,) float32/uint8 vertex data, added to ``binary``."""
    out = {
        "bufferView": binary.view(np.ascontiguousarray(data).tobytes(), ARRAY_BUFFER),
        "componentType": UBYTE if data.dtype == np.uint8 else FLOAT,
        "count": len(data),
        "type": kind,
    }
    if normalized:
        out["normalized"] = True
    if bounds:
        out["min"] = [float(v) for v in data.min(axis=0)]
        out["max"] = [float(v) for v in data.max(axis=0)]
    return out


def index_accessor(faces: np.ndarray, binary: Binary) -> dict:
    """An accessor over (m, 3) triangle vertex indices (uint32), added to ``binary``."""
    flat = np.ascontiguousarray(faces, dtype=np.uint32).ravel()
    return {"bufferView": binary.view(flat.tobytes(), ELEMENT_ARRAY_BUFFER), "componentType": UINT,
            "count": len(flat), "type": "SCALAR"}


def glb(doc: dict, binary: bytes) -> bytes:
    """A GLB container: 12-byte header, JSON chunk (space padded), BIN chunk (4-byte aligned)."""
    text = json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join([
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<II", len(text), 0x4E4F534A), text,
        struct.pack("<II", len(binary), 0x004E4942), binary,
    ])
