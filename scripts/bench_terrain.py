"""Benchmark: DSM, ground filter, DTM and nDSM as whole processes, beside PDAL.

A real tile (default: the Delft AHN3 strip) is copied on a kx x ky grid of shifted
copies and written as one LAZ in a temporary folder, so every contender starts from
the same file. Two cases are timed, each as a fresh process (imports, reading the LAZ
and writing GeoTIFFs included), alternating the contenders ``--repeat`` times and
keeping the median wall time and the peak RSS (``wait4``):

``dsm``
    recon3d: read, automatic cell, highest point per cell, small holes filled, DSM.tif.
    PDAL: ``readers.las`` -> ``writers.gdal`` (``output_type=max``) at the same cell.
``terrain``
    recon3d: the DSM, the ground filter (``GroundConfig()``), the DTM (Delaunay gap
    fill) and the nDSM, three GeoTIFFs. PDAL: ``filters.smrf`` (defaults) ->
    ``filters.range`` (class 2) -> ``writers.gdal`` (``output_type=idw``) for the DTM,
    and the DSM as above in the same pipeline.

Two rates are printed: points per second of the whole process (start-up, imports,
LAZ decoding and GeoTIFF writing included: what a user waits for, and what PDAL's
figure is), and for recon3d the rate of the terrain work alone (``compute``: the DSM,
ground, DTM and nDSM stages, medians over the runs), which LAZ decoding does not bound.

``--baseline DIR`` adds an older recon3d (a source tree, e.g. ``git archive REV | tar
-x -C DIR``) run the same way in the same benchmark, for before/after tables.

PDAL is a peer only, not a dependency: conda-forge's ``pdal``, Ubuntu's package, or on
Debian 12 and later (which do not package it) ``sudo sh scripts/pdal_chroot.sh``
(Debian 11's PDAL 2.2.0 in a folder of its own). Without it a full run refuses unless
``--no-pdal`` is given; ``--quick`` (one copy of the strip, one run) notes it and goes on.

    .venv/bin/python scripts/bench_terrain.py [--tiles 3 1] [--repeat 3] [--baseline DIR] [--no-pdal] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _bench

DATA = _bench.SHARED / "lidar" / "delft_ahn3_strip.laz"
CRS = "EPSG:7415"  # the Delft strip's, not in its header; a file with its own CRS keeps it


def write_tiled(data: Path, kx: int, ky: int, out: Path) -> int:
    """Write ``data`` copied kx x ky times (shifted by its extent) to ``out``; returns the point count."""
    import laspy
    import numpy as np

    las = laspy.read(data)
    h = las.header
    size = (h.maxs[:2] - h.mins[:2]) + 0.01
    parts = []
    for i in range(kx):
        for j in range(ky):
            a = las.points.array.copy()
            a["X"] += int(round(i * size[0] / h.scales[0]))
            a["Y"] += int(round(j * size[1] / h.scales[1]))
            parts.append(a)
    header = laspy.LasHeader(point_format=h.point_format, version=h.version)
    header.offsets, header.scales = h.offsets, h.scales
    header.vlrs.extend(h.vlrs)
    tiled = laspy.LasData(header)
    tiled.points = laspy.ScaleAwarePointRecord(np.concatenate(parts), h.point_format, h.scales, h.offsets)
    tiled.update_header()
    tiled.write(out)
    return len(tiled.points)


# -- the recon3d process -------------------------------------------------------------


def worker(path: Path, case: str, out: Path, crs: str | None, hole_area: float) -> None:
    """One recon3d run of ``case`` on ``path`` (this script re-run with --worker): prints its stage times as JSON."""
    import resource

    times, peaks = {}, {}

    def peak(stage: str) -> None:
        peaks[stage] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)

    t = time.perf_counter()
    from recon3d.config import GroundConfig
    from recon3d.core.geo import crs_units, parse_crs
    from recon3d.io.geotiff import write_raster
    from recon3d.io.las import read_las
    from recon3d.terrain import dsm, dtm, ground

    times["import"] = time.perf_counter() - t
    t = time.perf_counter()
    cloud = read_las(path, crs=parse_crs(crs) if crs else None)
    units = crs_units(cloud.crs)
    times["read"] = time.perf_counter() - t
    peak("read")
    t = time.perf_counter()
    res, _ = dsm.choose_resolution(dsm.point_spacing(cloud.xyz[:, :2]), units)
    surface = dsm.make_dsm(cloud, res, max_hole_cells=int(units.area(hole_area) / res**2))
    times["dsm"] = time.perf_counter() - t
    peak("dsm")
    products = {"dsm": surface}
    if case == "terrain":
        t = time.perf_counter()
        result = ground.classify_ground(cloud, GroundConfig(), units, res)
        times["ground"] = time.perf_counter() - t
        peak("ground")
        t = time.perf_counter()
        noise = result.params["noise"]["value"] / units.vertical
        products["dtm"] = dtm.make_dtm(cloud.xyz[result.for_dtm], surface, noise=noise)
        products["ndsm"] = dtm.make_ndsm(surface, products["dtm"])
        times["dtm+ndsm"] = time.perf_counter() - t
        peak("dtm+ndsm")
    t = time.perf_counter()
    for name, raster in products.items():
        write_raster(raster, out / f"{name}.tif")
    times["write"] = time.perf_counter() - t
    peak("write")
    print(json.dumps({"resolution": res, "shape": list(surface.shape), "times": times, "peak_mb_after": peaks}))


def run_process(cmd: list[str], env: dict | None = None) -> tuple[float, float, str]:
    """Run ``cmd``; returns (wall seconds, peak RSS MB of that process, stdout). Raises on a non-zero exit."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        if proc.returncode:
            raise RuntimeError(f"{Path(cmd[0]).name} failed ({proc.returncode}): {err.read().strip()[-600:]}")
        return wall, usage.ru_maxrss / 1024, out.read()


def auto_resolution(path: Path, crs: str | None) -> float:
    """The DSM cell recon3d picks for ``path``, given to PDAL so both grid alike."""
    from recon3d.core.geo import crs_units, parse_crs
    from recon3d.io.las import read_las
    from recon3d.terrain import dsm

    cloud = read_las(path, crs=parse_crs(crs) if crs else None)
    return dsm.choose_resolution(dsm.point_spacing(cloud.xyz[:, :2]), crs_units(cloud.crs))[0]


def recon3d_cmd(source: Path, path: Path, case: str, out: Path, crs: str | None) -> tuple[list[str], dict]:
    """The worker's command line: the terrain modules alone are imported, not the whole pipeline."""
    from recon3d.pipeline.run import HOLE_AREA

    env = os.environ | {"PYTHONPATH": str(source)}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(path), "--case", case, "--out", str(out),
           "--hole-area", str(HOLE_AREA["lidar"][0])]
    return cmd + (["--crs", crs] if crs else []), env


# -- the PDAL process ----------------------------------------------------------------


def pdal_pipeline(path: Path, case: str, out: Path, resolution: float) -> list:
    dsm = {"type": "writers.gdal", "filename": str(out / "pdal_dsm.tif"), "resolution": resolution,
           "output_type": "max", "data_type": "float32"}
    if case == "dsm":
        return [str(path), dsm]
    return [
        str(path),
        dsm,
        {"type": "filters.smrf"},
        {"type": "filters.range", "limits": "Classification[2:2]"},
        {"type": "writers.gdal", "filename": str(out / "pdal_dtm.tif"), "resolution": resolution,
         "output_type": "idw", "window_size": 8, "data_type": "float32"},
    ]


def pdal_cmd(path: Path, case: str, out: Path, resolution: float) -> list[str]:
    spec = out / f"pdal_{case}.json"
    spec.write_text(json.dumps({"pipeline": pdal_pipeline(path, case, out, resolution)}))
    return _bench.pdal_command("pipeline", str(spec))


# -- driver --------------------------------------------------------------------------


def measure(contenders: dict, repeat: int, quick: bool) -> dict:
    """Median wall time and peak RSS of each contender, their runs alternating; a failed peer left out."""
    runs = {name: [] for name in contenders}
    for _ in range(repeat):
        for name, (cmd, env) in contenders.items():
            if name not in runs:
                continue
            try:
                runs[name].append(run_process(cmd, env))
            except RuntimeError as exc:
                if name.startswith("recon3d"):
                    raise
                _bench.peer_failed(name, str(exc), quick)
                del runs[name]
    out = {}
    for name, rs in runs.items():
        out[name] = {"wall_s": statistics.median(r[0] for r in rs), "peak_rss_mb": max(r[1] for r in rs)}
        printed = [r[2].strip().splitlines() for r in rs]
        stages = [json.loads(lines[-1])["times"] for lines in printed if lines and lines[-1].startswith("{")]
        if stages:
            out[name]["stages_s"] = {k: statistics.median(t[k] for t in stages) for k in stages[0]}
            out[name]["compute_s"] = sum(v for k, v in out[name]["stages_s"].items() if k not in NOT_COMPUTE)
    return out


#: Worker stages that are not the terrain work itself: the compute rate leaves them out.
NOT_COMPUTE = ("import", "read", "write")


def print_case(case: str, n: int, figures: dict) -> None:
    print(f"\n{case}: {n:,} points")
    print(f"  {'contender':<16}{'wall s':>9}{'peak MB':>10}{'M pts/s':>9}{'compute':>9}  stages (median, s)")
    for name, f in figures.items():
        stages = " ".join(f"{k} {v:.2f}" for k, v in f.get("stages_s", {}).items())
        compute = f"{n / f['compute_s'] / 1e6:9.2f}" if f.get("compute_s") else f"{'-':>9}"
        print(f"  {name:<16}{f['wall_s']:9.2f}{f['peak_rss_mb']:10.0f}{n / f['wall_s'] / 1e6:9.2f}{compute}  {stages}")
    print("  M pts/s: points over the whole process's wall time (start, imports, LAZ decoding and "
          "GeoTIFF writing included); compute: over the stages between reading and writing")
    ours = figures["recon3d"]
    for peer in (p for p in figures if p != "recon3d"):
        _bench.print_ratios(case, peer, {"wall": ours["wall_s"], "rss": ours["peak_rss_mb"]},
                            {"wall": figures[peer]["wall_s"], "rss": figures[peer]["peak_rss_mb"]},
                            [("wall", "wall s"), ("rss", "peak RSS MB")])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiles", type=int, nargs=2, default=(3, 1), metavar=("KX", "KY"),
                        help="copies of the tile across and up (default: %(default)s; 9 3 for 5.6M points)")
    parser.add_argument("--data", type=Path, default=DATA, help="LAS/LAZ file to tile (default: %(default)s)")
    parser.add_argument("--repeat", type=int, default=3, help="alternating runs per contender; median kept")
    parser.add_argument("--cases", default="dsm,terrain", help="comma-separated: dsm, terrain")
    parser.add_argument("--baseline", type=Path, help="an older recon3d source tree to time beside this one")
    parser.add_argument("--no-pdal", action="store_true", help="run without PDAL")
    parser.add_argument("--json", type=Path, help="write every figure here")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--case", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--crs", help=argparse.SUPPRESS)
    parser.add_argument("--hole-area", type=float, help=argparse.SUPPRESS)
    _bench.add_quick(parser)
    args = parser.parse_args()
    if args.worker:
        return worker(args.worker, args.case, args.out, args.crs, args.hole_area)
    if args.quick:
        args.tiles, args.repeat = (1, 1), 1
    if min(args.tiles) < 1 or args.repeat < 1:
        _bench.refuse(f"--tiles {args.tiles} --repeat {args.repeat}: at least 1 each")
    if args.baseline is not None and not (args.baseline / "recon3d").is_dir():
        _bench.refuse(f"--baseline {args.baseline}: no recon3d package in it")
    data = _bench.require(args.data, "LiDAR file")
    crs = CRS if data.name == DATA.name else None
    pdal = _bench.use_pdal(args.no_pdal, args.quick)
    record = {"data": str(data), "tiles": list(args.tiles), "repeat": args.repeat, "cases": {}}
    with tempfile.TemporaryDirectory(prefix="bench_terrain_") as tmp:
        tmp = Path(tmp)
        path = tmp / "tiled.laz"
        n = write_tiled(data, *args.tiles, path)
        resolution = auto_resolution(path, crs) if pdal else None
        for case in args.cases.split(","):
            contenders = {}
            for name, source in (("recon3d", _bench.ROOT), ("recon3d before", args.baseline)):
                if source is not None:
                    folder = tmp / name.replace(" ", "_")
                    folder.mkdir(exist_ok=True)
                    contenders[name] = recon3d_cmd(source, path, case, folder, crs)
            if pdal:
                contenders["PDAL"] = (pdal_cmd(path, case, tmp, resolution), None)
            figures = measure(contenders, args.repeat, args.quick)
            record["cases"][case] = {"points": n, "figures": figures}
            print_case(case, n, figures)
    if args.json:
        args.json.write_text(json.dumps(record, indent=2))


if __name__ == "__main__":
    _bench.guard(main)
