"""Peer comparison of recon3d's satellite (RPC) stereo path with s2p.

s2p (the Satellite Stereo Pipeline of CNES / ENS Paris-Saclay, ``pip install s2p``)
is an independent, widely used implementation of the same job recon3d's satellite
path does: two images with RPC camera models in, a DSM in UTM out. This script runs
it on one pair, so that recon3d's numbers on the same pair have a reference.

Usage::

    .venv/bin/python scripts/peer_s2p.py IMG1 IMG2 -o OUT_DIR \
        [--s2p /work/peers/.venv-s2p/bin/s2p] [--truth TRUTH_DSM.tif]

s2p is not a dependency of recon3d: it lives in its own virtual environment
(default executable ``/work/peers/.venv-s2p/bin/s2p``, else ``s2p`` on PATH) and is
run in a subprocess. This script itself needs only the standard library, numpy and
rasterio, so it runs with recon3d's own python.

What it does

1. Reads each image's RPC: from the GeoTIFF RPC tags (s2p then reads them itself
   through rpcm), else from an OSSIM keyword list beside the image (``img1.geom``,
   ``type: ossimRpcModel``, ``polynomial_format: B``), which describes the full scene;
   when the image is a crop whose geotransform is a pure pixel offset (as recon3d's
   ``read_rpc_camera`` assumes), the offset is taken out of the RPC line/sample
   offsets. That RPC goes into the config as an rpcm dict. An image with neither is
   refused with a message.
2. Writes ``OUT_DIR/config.json``: the whole first image as ROI, ``dsm_resolution``
   0.5 m, ``use_srtm`` false and no exogenous DEM, ``disp_range_method`` "sift" (the
   disparity range comes from SIFT matches, so nothing is downloaded at run time:
   s2p's SRTM option fetches tiles from the internet), one process per core and, when
   there are fewer tiles than cores, the spare cores as OpenMP threads of the matcher.
3. Runs s2p, logs to ``OUT_DIR/s2p.log``, and prints ``DSM: <absolute path>``
   (s2p writes ``OUT_DIR/dsm.tif``), the wall time, the DSM's grid and the share of
   finite cells.
4. With ``--truth``: resamples s2p's DSM bilinearly onto the truth grid
   (``rasterio.warp.reproject``) and prints, over the cells where both are finite,
   the median, NMAD (1.4826 * median |e - median e|) and share within 1 m of
   e = s2p - truth, and the coverage (those cells over the truth's finite cells).

Heights: s2p triangulates with the RPC localisation functions, whose height axis is
the WGS84 ellipsoid (EPSG:4979), and converts to the output CRS with pyproj. With the
default output CRS (local UTM zone, no vertical datum) the heights stay ellipsoidal;
only an ``out_crs`` with a vertical datum (e.g. ``epsg:32636+5773``) would turn them
into geoid heights. The script reports what the written DSM's CRS says.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import rasterio
from rasterio.errors import NotGeoreferencedWarning
from rasterio.warp import Resampling, reproject

DEFAULT_S2P = Path("/work/peers/.venv-s2p/bin/s2p")

_GEOM_KEYS = {  # rpcm attribute -> OSSIM keyword
    "row_offset": "line_off",
    "col_offset": "samp_off",
    "lat_offset": "lat_off",
    "lon_offset": "long_off",
    "alt_offset": "height_off",
    "row_scale": "line_scale",
    "col_scale": "samp_scale",
    "lat_scale": "lat_scale",
    "lon_scale": "long_scale",
    "alt_scale": "height_scale",
}
_GEOM_COEFFS = {
    "row_num": "line_num_coeff",
    "row_den": "line_den_coeff",
    "col_num": "samp_num_coeff",
    "col_den": "samp_den_coeff",
}


class PeerError(Exception):
    """A problem with the inputs or with the s2p run, reported without a traceback."""


def read_geom(path: Path) -> dict:
    """An OSSIM ``ossimRpcModel`` keyword list as an rpcm ``__dict__`` (full scene)."""
    kw = {}
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, value = line.partition(":")
        if sep:
            kw[key.strip()] = value.strip()
    kind = kw.get("type", "ossimRpcModel")
    if kind != "ossimRpcModel":
        raise PeerError(f"{path}: OSSIM model type {kind!r} is not an RPC model (ossimRpcModel)")
    if kw.get("polynomial_format", "B").upper() != "B":
        raise PeerError(f"{path}: RPC polynomial_format {kw['polynomial_format']!r} (only B)")
    try:
        d = {attr: float(kw[key]) for attr, key in _GEOM_KEYS.items()}
        for attr, key in _GEOM_COEFFS.items():
            d[attr] = [float(kw[f"{key}_{i:02d}"]) for i in range(20)]
    except KeyError as exc:
        raise PeerError(f"{path}: not an OSSIM RPC keyword list (missing {exc.args[0]})") from None
    except ValueError as exc:
        raise PeerError(f"{path}: non-numeric RPC value ({exc})") from None
    return d


def image_entry(img: Path) -> tuple[dict, str, tuple[int, int]]:
    """The s2p ``images`` entry for one image, where its RPC came from, and (w, h)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(img) as src:
            has_tags = bool(src.tags(ns="RPC"))
            t = src.transform
            size = (src.width, src.height)
    if has_tags:
        return {"img": str(img)}, "GeoTIFF RPC tags (read by s2p via rpcm)", size
    geom = img.with_suffix(".geom")
    if not geom.is_file():
        raise PeerError(
            f"{img}: no RPC in the GeoTIFF tags and no {geom.name} beside it; "
            "s2p needs an RPC model for every image (skipped)"
        )
    rpc = read_geom(geom)
    col0 = row0 = 0.0
    if (t.a, t.b, t.d, t.e) == (1.0, 0.0, 0.0, 1.0):  # crop of a non-georeferenced scene
        col0, row0 = float(t.c), float(t.f)
        rpc["col_offset"] -= col0
        rpc["row_offset"] -= row0
    where = f"{geom} (OSSIM keyword list, crop offset col {col0:g} row {row0:g} applied)"
    return {"img": str(img), "rpc": rpc}, where, size


def find_s2p(given: str | None) -> str:
    if given:
        exe = shutil.which(given) or (given if Path(given).is_file() else None)
        if not exe:
            raise PeerError(f"s2p executable not found: {given}")
        return str(Path(exe).absolute())
    if DEFAULT_S2P.is_file():
        return str(DEFAULT_S2P)
    exe = shutil.which("s2p")
    if not exe:
        raise PeerError(
            f"no s2p executable ({DEFAULT_S2P} missing and none on PATH); "
            "give one with --s2p"
        )
    return exe


def count_tiles(w: int, h: int, tile: int) -> int:
    """The number of tiles s2p cuts a w x h ROI into (as its ``adjust_tile_size``)."""
    nx = max(1, round(w / min(w, tile)))
    ny = max(1, round(h / min(h, tile)))
    return nx * ny


def write_config(img1: Path, img2: Path, out_dir: Path, args) -> tuple[Path, dict]:
    entries = []
    for img in (img1, img2):
        entry, where, size = image_entry(img)
        print(f"{img.name}: {size[0]} x {size[1]} px, RPC from {where}")
        entries.append((entry, size))
    w, h = entries[0][1]
    omp = args.omp_threads
    if omp is None:  # s2p runs one process per tile: give the spare cores to mgm's OpenMP
        omp = max(1, args.processes // min(count_tiles(w, h, args.tile_size), args.processes))
    cfg = {
        "out_dir": str(out_dir),
        "temporary_dir": str(out_dir / "s2p_tmp"),
        "images": [e for e, _ in entries],
        "roi": {"x": 0, "y": 0, "w": int(w), "h": int(h)},
        "dsm_resolution": args.dsm_resolution,
        "use_srtm": False,
        "exogenous_dem": None,
        "disp_range_method": "sift",
        "matching_algorithm": "mgm",
        "tile_size": args.tile_size,
        "max_processes": args.processes,
        "omp_num_threads": omp,
        "clean_tmp": True,
    }
    path = out_dir / "config.json"
    path.write_text(json.dumps(cfg, indent=2))
    return path, cfg


def run_s2p(exe: str, config: Path, out_dir: Path, timeout: float) -> float:
    log_path = out_dir / "s2p.log"
    t0 = time.perf_counter()
    with open(log_path, "w") as log:
        try:
            proc = subprocess.run(
                [exe, str(config)], stdout=log, stderr=subprocess.STDOUT,
                cwd=out_dir, timeout=timeout,
            )
        except subprocess.TimeoutExpired:
            raise PeerError(f"s2p did not finish in {timeout:g} s (log: {log_path})") from None
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = log_path.read_text(errors="replace").splitlines()[-25:]
        raise PeerError(
            f"s2p exited with code {proc.returncode} after {wall:.1f} s; last lines of "
            f"{log_path}:\n" + "\n".join(tail)
        )
    return wall


def height_datum(crs) -> str:
    """What the DSM's CRS says about its heights."""
    if crs is None:
        return "unknown (no CRS in the DSM)"
    wkt = crs.to_wkt()
    if "VERTCRS" in wkt or "VERT_CS" in wkt:
        return f"geoid / vertical datum in the CRS ({crs})"
    return (
        f"ellipsoidal (WGS84): horizontal-only CRS {crs.to_string()}, heights kept on "
        "the RPC height axis (EPSG:4979 ellipsoid)"
    )


def compare(dsm_path: Path, truth_path: Path) -> dict:
    with rasterio.open(truth_path) as t:
        truth = t.read(1, masked=True).astype(np.float64).filled(np.nan)
        t_transform, t_crs = t.transform, t.crs
    resampled = np.full(truth.shape, np.nan, dtype=np.float64)
    with rasterio.open(dsm_path) as s:
        src = s.read(1, masked=True).astype(np.float64).filled(np.nan)
        reproject(
            source=src, destination=resampled,
            src_transform=s.transform, src_crs=s.crs, src_nodata=np.nan,
            dst_transform=t_transform, dst_crs=t_crs, dst_nodata=np.nan,
            resampling=Resampling.bilinear,
        )
    truth_ok = np.isfinite(truth)
    both = truth_ok & np.isfinite(resampled)
    e = resampled[both] - truth[both]
    if e.size == 0:
        return {"n": 0, "coverage": 0.0}
    med = float(np.median(e))
    return {
        "n": int(e.size),
        "coverage": float(both.sum() / max(truth_ok.sum(), 1)),
        "median": med,
        "nmad": float(1.4826 * np.median(np.abs(e - med))),
        "within_1m": float(np.mean(np.abs(e) <= 1.0)),
        "mean": float(e.mean()),
        "rmse": float(math.sqrt(np.mean(e ** 2))),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("img1", type=Path, help="reference image (GeoTIFF, RPC tags or .geom beside)")
    p.add_argument("img2", type=Path, help="secondary image")
    p.add_argument("-o", "--out", type=Path, required=True, help="s2p output directory")
    p.add_argument("--s2p", help=f"s2p executable (default {DEFAULT_S2P}, else on PATH)")
    p.add_argument("--truth", type=Path, help="truth DSM GeoTIFF (ellipsoidal heights)")
    p.add_argument("--dsm-resolution", type=float, default=0.5, help="m per cell (0.5)")
    p.add_argument("--tile-size", type=int, default=800, help="s2p tile size in px (800)")
    p.add_argument("--processes", type=int, default=os.cpu_count() or 1,
                   help="s2p max_processes (number of cores)")
    p.add_argument("--omp-threads", type=int, default=None,
                   help="OpenMP threads per s2p matching process (default: cores / tiles)")
    p.add_argument("--timeout", type=float, default=3600.0, help="s (3600)")
    args = p.parse_args(argv)

    try:
        img1, img2 = args.img1.resolve(), args.img2.resolve()
        for img in (img1, img2):
            if not img.is_file():
                raise PeerError(f"image not found: {img}")
        if args.truth is not None and not args.truth.is_file():
            raise PeerError(f"truth DSM not found: {args.truth}")
        exe = find_s2p(args.s2p)
        out_dir = args.out.resolve()
        out_dir.mkdir(parents=True, exist_ok=True)
        stale = out_dir / "dsm.tif"
        if stale.exists():
            stale.unlink()
        config, _ = write_config(img1, img2, out_dir, args)
        print(f"config: {config}")
        print(f"running: {exe} {config}")
        wall = run_s2p(exe, config, out_dir, args.timeout)
        dsm = out_dir / "dsm.tif"
        if not dsm.is_file():
            raise PeerError(f"s2p finished but wrote no {dsm} (see {out_dir / 's2p.log'})")
    except PeerError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1

    with rasterio.open(dsm) as s:
        z = s.read(1, masked=True).astype(np.float64).filled(np.nan)
        crs, res = s.crs, s.res
    finite = np.isfinite(z)
    print(f"DSM: {dsm}")
    print(f"wall time: {wall:.1f} s")
    print(f"grid: {z.shape[1]} x {z.shape[0]} cells at {res[0]:g} x {res[1]:g} m, CRS {crs}")
    print(f"finite: {finite.mean():.1%} of the DSM's cells")
    if finite.any():
        print(f"height range: {np.nanmin(z):.2f} .. {np.nanmax(z):.2f} m")
    print(f"heights: {height_datum(crs)}")

    if args.truth is not None:
        r = compare(dsm, args.truth)
        if r["n"] == 0:
            print("vs truth: no cell where both s2p and the truth are finite")
            return 1
        print(
            f"vs truth ({args.truth}): n={r['n']} cells, coverage {r['coverage']:.1%} of the "
            f"truth's finite cells"
        )
        print(
            f"  median {r['median']:+.3f} m, NMAD {r['nmad']:.3f} m, "
            f"within 1 m {r['within_1m']:.1%} (mean {r['mean']:+.3f} m, RMSE {r['rmse']:.3f} m)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
