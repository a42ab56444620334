"""Fuzzed readers: a damaged file is read or refused with recon3d's own error, never anything else.

Each reader gets a small valid file with random truncations, byte flips and runs of
extreme bytes (hypothesis, a few hundred cases per reader in the suite;
``scripts/fuzz_readers.py`` runs 10,000 per reader). ``--set`` parsing gets random
text.
"""

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon3d.errors import Recon3dError

#: The same 150 damaged files on every run, so that a red suite names a reproducible
#: file; with ``derandomize=False`` a local run explores further, and what it finds
#: becomes a test of its own (as test_raster_with_undecodable_tag_text_is_refused).
FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


def _las_bytes() -> bytes:
    import laspy

    rng = np.random.default_rng(0)
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales, header.offsets = [0.01] * 3, [5e5, 5e6, 0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = (rng.uniform(0, 50, 200) + o for o in (5e5, 5e6, 10))
    las.classification = rng.integers(1, 7, 200).astype(np.uint8)
    with tempfile.TemporaryDirectory() as tmp:
        las.write(Path(tmp) / "a.las")
        return (Path(tmp) / "a.las").read_bytes()


def _tif_bytes() -> bytes:
    from affine import Affine

    from recon3d.core.geo import parse_crs
    from recon3d.core.raster import Raster
    from recon3d.io.geotiff import write_raster

    data = np.arange(64 * 64, dtype=np.float32).reshape(64, 64)
    with tempfile.TemporaryDirectory() as tmp:
        write_raster(Raster(data, Affine(1, 0, 5e5, 0, -1, 5e6), parse_crs("EPSG:32631")), Path(tmp) / "a.tif")
        return (Path(tmp) / "a.tif").read_bytes()


def _cityjson_bytes() -> bytes:
    doc = {"type": "CityJSON", "version": "2.0", "transform": {"scale": [0.001] * 3, "translate": [5e5, 5e6, 0]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/32631"},
           "CityObjects": {"b1": {"type": "Building", "attributes": {"measuredHeight": 6.0}, "geometry": [
               {"type": "Solid", "lod": "1", "boundaries": [[[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4]],
                                                             [[1, 2, 6, 5]], [[2, 3, 7, 6]], [[3, 0, 4, 7]]]]}]}},
           "vertices": [[0, 0, 0], [10000, 0, 0], [10000, 10000, 0], [0, 10000, 0],
                        [0, 0, 6000], [10000, 0, 6000], [10000, 10000, 6000], [0, 10000, 6000]]}
    return json.dumps(doc).encode()


def _ply_bytes() -> bytes:
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 50, (100, 3))
    head = "ply\nformat ascii 1.0\nelement vertex 100\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    return (head + "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts) + "\n").encode()


def _read_las(path):
    from recon3d.core.geo import parse_crs
    from recon3d.io.las import read_las

    return read_las(path, crs=parse_crs("EPSG:32631"))


def _read_tif(path):
    from recon3d.io.geotiff import read_raster

    return read_raster(path)


def _read_cityjson(path):
    from recon3d.io.cityjson import read_cityjson

    return read_cityjson(path)


def _read_ply(path):
    from recon3d.core.geo import parse_crs
    from recon3d.io.ply import read_ply

    return read_ply(path, crs=parse_crs("EPSG:32631"))


def _geom_bytes() -> bytes:
    from conftest import shared

    return shared("stereo/pleiades_gizeh/img1.geom").read_bytes()


def _read_geom(path):
    from recon3d.io.rpc import RPCModel

    return RPCModel.from_geom(path)


READERS = {
    "geom": (_geom_bytes, _read_geom, ".geom"),
    "las": (_las_bytes, _read_las, ".las"),
    "tif": (_tif_bytes, _read_tif, ".tif"),
    "cityjson": (_cityjson_bytes, _read_cityjson, ".city.json"),
    "ply": (_ply_bytes, _read_ply, ".ply"),
}
_BASE: dict[str, bytes] = {}


@st.composite
def damage(draw, size: int):
    """(truncate_at or None, [(offset, byte)...]): a cut and a few flipped or extreme bytes."""
    cut = draw(st.one_of(st.none(), st.integers(0, max(size - 1, 0))))
    flips = draw(st.lists(st.tuples(st.integers(0, max(size - 1, 0)), st.sampled_from([0, 1, 0x7F, 0x80, 0xFF])
                                    | st.integers(0, 255)), max_size=8))
    return cut, flips


def spoil(data: bytes, cut, flips) -> bytes:
    out = bytearray(data)
    for offset, value in flips:
        if offset < len(out):
            out[offset] = value
    return bytes(out[:cut] if cut is not None else out)


@pytest.mark.parametrize("kind", sorted(READERS))
def test_damaged_files_are_read_or_refused(kind, tmp_path):
    make, read, suffix = READERS[kind]
    base = _BASE.setdefault(kind, make())
    read_ok = read(_write(tmp_path, base, suffix))  # the undamaged file reads
    assert read_ok is not None

    @FUZZ
    @given(damage(len(base)))
    def check(mutation):
        path = _write(tmp_path, spoil(base, *mutation), suffix)
        try:
            read(path)
        except Recon3dError:
            pass

    check()


def _write(folder: Path, data: bytes, suffix: str) -> Path:
    path = folder / f"input{suffix}"
    path.write_bytes(data)
    return path


@FUZZ
@given(st.text(max_size=60))
def test_set_parsing(text):
    from recon3d.config import PipelineConfig

    for item in (text, f"dsm.resolution={text}", f"lod.lods={text}", f"ground.{text}"):
        try:
            PipelineConfig().with_overrides([item])
        except Recon3dError:
            pass


def test_damaged_colmap_models(tmp_path):
    """Text COLMAP models with lines cut, fields dropped or numbers replaced."""
    from recon3d.io.colmap import read_scene

    rng = np.random.default_rng(3)
    from recon3d.synthetic.family import CONFIGURATIONS
    from recon3d.synthetic.scene import write_block_scene

    good = tmp_path / "good"
    write_block_scene(good, CONFIGURATIONS["nadir_pair"].with_width(160))
    for trial in range(60):
        scene = tmp_path / f"s{trial}"
        shutil.copytree(good, scene)
        target = scene / "sparse" / rng.choice(["cameras.txt", "images.txt", "points3D.txt"])
        lines = target.read_text().splitlines()
        k = int(rng.integers(0, len(lines)))
        words = lines[k].split()
        action = trial % 3
        if action == 0 and words:
            words = words[: int(rng.integers(0, len(words)))]
        elif action == 1 and words:
            words[int(rng.integers(0, len(words)))] = rng.choice(["nan", "-1", "1e308", "x", ""])
        else:
            lines = lines[:k]
        if action < 2:
            lines[k] = " ".join(words)
        target.write_text("\n".join(lines) + "\n")
        try:
            read_scene(scene)
        except Recon3dError:
            pass
        shutil.rmtree(scene)


def test_raster_with_undecodable_tag_text_is_refused(tmp_path):
    # found by the fuzzing above: a byte of the GeoTIFF's ASCII parameters made invalid
    # UTF-8, which rasterio raised as a UnicodeDecodeError instead of its own error
    make, read, suffix = READERS["tif"]
    path = _write(tmp_path, spoil(_BASE.setdefault("tif", make()), None, [(541, 0), (550, 128)]), suffix)
    with pytest.raises(Recon3dError, match="cannot read raster"):
        read(path)
