"""Benchmark: LoD2.2 buildings per second (roof planes + solids + validation).

Two workloads, timed on :func:`recon3d.buildings.lod.build_lods` alone (the call the
pipeline makes per building: roof segmentation, LoD2.2 solid, its check_solid, the
LoD1 block and, where LoD2.2 fails, the LoD1.3 fallback):

``3dbag``
    The 10 LoD2.2 buildings of ``citymodels/multi_lod.json`` (3DBAG), their roof
    surfaces sampled into clouds of 12 points/m2 with 5 cm noise plus wall and ground
    points, each building sampled ``--copies`` times with different seeds.
``delft``
    The buildings ``recon3d run`` finds in the Delft AHN3 strip (the pipeline is run
    once to get footprints, terrain and roof heights; its time is not counted), each
    with the points the pipeline gives it: neither ground nor vegetation, in its box.

Each workload runs with 1 and with 2 worker processes (``--workers``); Open3D is held
to one thread per process by ``recon3d.buildings.roofs``. Reported: buildings per
second (wall clock, best of ``--repeat``), how many got LoD2.2 and the reasons of the
others, and the median / 90th percentile time per building in one process.

``--quick``: the 3DBAG workload once, one copy, one worker.

    .venv/bin/python scripts/bench_roofs.py [--data DIR] [--copies N] [--repeat N] [--workers 1,2] [--json PATH] [--quick]
"""

from __future__ import annotations

import argparse
import collections
import json
import multiprocessing as mp
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import _bench
import numpy as np
import shapely

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = _bench.SHARED
LODS = ("1", "2.2")
INPUTS = {"3dbag": "citymodels/multi_lod.json", "delft": "lidar/delft_ahn3_strip.laz"}


def sample_roofs(city, copies: int, density: float = 12.0, seed: int = 0):
    """(footprint, world points, ground_z, roof_z) jobs from a city model's LoD2.2 roofs."""
    from recon3d.quality.roofs import roof_height_at

    rng = np.random.default_rng(seed)
    jobs = []
    for _ in range(copies):
        for b in city.buildings:
            solid = b.solids.get("2.2") or b.solids.get("2")
            if solid is None:
                continue
            mesh = solid.to_trimesh()
            sem = np.asarray(mesh.metadata["semantics"])
            tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
            pts = []
            for kind, per_area in (("RoofSurface", density), ("WallSurface", 1.0)):
                t = tri[sem == kind]
                cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
                area = 0.5 * (np.abs(cross[:, 2]) if kind == "RoofSurface" else np.linalg.norm(cross, axis=1))
                idx = np.repeat(np.arange(len(t)), rng.poisson(area * per_area))
                r1, r2 = rng.random(len(idx)), rng.random(len(idx))
                flip = r1 + r2 > 1
                r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
                p = t[idx, 0] + r1[:, None] * (t[idx, 1] - t[idx, 0]) + r2[:, None] * (t[idx, 2] - t[idx, 0])
                if kind == "RoofSurface":
                    p = p[p[:, 2] >= roof_height_at(solid, p[:, :2]) - 0.01]
                pts.append(p)
            local = np.concatenate(pts)
            local[:, 2] += rng.normal(0, 0.05, len(local))
            ground_z = float(solid.vertices[:, 2].min())
            fp_local = shapely.transform(b.footprint, lambda c: c - np.asarray(city.frame.origin[:2]))
            ring = fp_local.buffer(3.0).difference(fp_local)
            x0, y0, x1, y1 = ring.bounds
            g = rng.uniform([x0, y0], [x1, y1], (int(ring.envelope.area * density), 2))
            g = g[shapely.contains_xy(ring, g[:, 0], g[:, 1])]
            local = np.concatenate([local, np.column_stack([g, np.full(len(g), ground_z)])])
            world = city.frame.to_world(local)
            roof_z = float(np.percentile(local[local[:, 2] > ground_z + 1, 2], 90)) + city.frame.origin[2]
            jobs.append((b.footprint, world, ground_z + city.frame.origin[2], roof_z))
    return jobs, city.frame, None


def delft_jobs(data: Path):
    """Jobs from the buildings the pipeline finds in the Delft strip."""
    from recon3d.core.geo import parse_crs
    from recon3d.pipeline.run import run

    out = Path(tempfile.mkdtemp()) / "out"
    state = run(data / "lidar" / "delft_ahn3_strip.laz", out, crs=parse_crs("EPSG:7415"))
    xyz = state.cloud.xyz[~state.is_ground & ~state.vegetation]  # what build_solids hands a building: points that may lie on roofs
    jobs = []
    for b in state.city.buildings:
        if not (np.isfinite(b.ground_z) and np.isfinite(b.roof_z)):
            continue
        x0, y0, x1, y1 = b.footprint.bounds
        m = (xyz[:, 0] >= x0) & (xyz[:, 0] <= x1) & (xyz[:, 1] >= y0) & (xyz[:, 1] <= y1)
        jobs.append((b.footprint, xyz[m], b.ground_z, b.roof_z))
    return jobs, state.city.frame, state.units


_STATE: dict = {}


def _init(frame, units):
    from recon3d.buildings import lod
    from recon3d.config import LodConfig

    _STATE.update(frame=frame, units=units, config=LodConfig(lods=LODS))
    # warm up imports (Open3D, rasterio) outside the timed part
    lod.build_lods(shapely.box(0, 0, 10, 10), np.zeros((0, 3)), 0.0, 5.0, frame, _STATE["config"])


def _one(job):
    from recon3d.buildings import lod

    start = time.perf_counter()
    r = lod.build_lods(*job, _STATE["frame"], _STATE["config"], units=_STATE["units"])
    return r.status, r.reason, "2.2" in r.solids, time.perf_counter() - start


def bench(jobs, frame, units, workers: int, repeat: int) -> dict:
    best, results = None, None
    ctx = mp.get_context("fork")
    for _ in range(repeat):
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(frame, units)) as pool:
            list(pool.map(_one, jobs[: workers * 2]))  # every worker warmed up
            start = time.perf_counter()
            out = list(pool.map(_one, jobs, chunksize=1))
            wall = time.perf_counter() - start
        if best is None or wall < best:
            best, results = wall, out
    n22 = sum(r[2] for r in results)
    times = np.array([r[3] for r in results])
    reasons = collections.Counter(r[1] for r in results if not r[2])
    return {
        "workers": workers,
        "buildings": len(jobs),
        "lod22": int(n22),
        "other_reasons": dict(reasons),
        "wall_s": round(best, 3),
        "buildings_per_s": round(len(jobs) / best, 1),
        "lod22_per_s": round(n22 / best, 1),
        "median_ms": round(1000 * float(np.median(times)), 1),
        "p90_ms": round(1000 * float(np.percentile(times, 90)), 1),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--copies", type=int, default=5)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--workers", default="1,2")
    parser.add_argument("--only", choices=("3dbag", "delft"))
    parser.add_argument("--json", type=Path)
    _bench.add_quick(parser)
    args = parser.parse_args(argv)
    if args.quick:
        args.only, args.copies, args.repeat, args.workers = "3dbag", 1, 1, "1"
    for name, relative in INPUTS.items():
        if args.only in (None, name):
            _bench.require(args.data / relative, f"{name} input")
    sys.path.insert(0, str(ROOT))
    from recon3d.io.cityjson import read_cityjson

    workloads = {}
    if args.only in (None, "3dbag"):
        city = read_cityjson(args.data / "citymodels" / "multi_lod.json")
        workloads["3dbag"] = sample_roofs(city, args.copies)
    if args.only in (None, "delft"):
        workloads["delft"] = delft_jobs(args.data)
    report = {}
    for name, (jobs, frame, units) in workloads.items():
        for workers in (int(w) for w in args.workers.split(",")):
            row = bench(jobs, frame, units, workers, args.repeat)
            report[f"{name}/{workers}"] = row
            print(
                f"{name:6s} workers {workers}: {row['buildings']} buildings, {row['lod22']} LoD2.2, "
                f"{row['buildings_per_s']} buildings/s ({row['lod22_per_s']} LoD2.2/s), "
                f"median {row['median_ms']} ms, p90 {row['p90_ms']} ms, others {row['other_reasons']}"
            )
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    _bench.guard(main)
