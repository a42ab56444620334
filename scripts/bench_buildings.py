"""Benchmark: building detection and outlines per building on the shared LiDAR tiles.

Runs the pipeline, then times building detection with outlines the way the pipeline
calls it (blobs, split, trees rejected, outlines regularised; the vegetation
classification before it is not counted), the fastest of three runs.
Issue target: <= 20 ms per building on 2 cores. ``--quick``: the IGN village alone.

    .venv/bin/python scripts/bench_buildings.py [--data DIR] [--quick]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import _bench

from recon3d.buildings import detect, vegetation
from recon3d.core.geo import parse_crs
from recon3d.pipeline.run import run

DATA = _bench.SHARED / "lidar"
CASES = {"delft_ahn3_strip.laz": "EPSG:7415", "ign_village_2154.laz": None}
QUICK_CASES = ("ign_village_2154.laz",)


def time_detection(state) -> tuple[float, int]:
    """Fastest of three detection runs (s) and the number of buildings."""
    cfg, u = state.config.buildings, state.units
    veg = vegetation.classify_vegetation(state.cloud, state.dtm, cfg, u)
    share = vegetation.vegetation_cells(state.cloud, state.dsm, veg, share=True)
    times, polygons = [], []
    for _ in range(3):
        start = time.perf_counter()
        polygons = detect.detect_buildings(state.ndsm, share, cfg, u, cloud=state.cloud, dtm=state.dtm, point_vegetation=veg)
        times.append(time.perf_counter() - start)
    return min(times), len(polygons)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="folder of the LiDAR files (default: %(default)s)")
    _bench.add_quick(parser)
    args = parser.parse_args()
    names = QUICK_CASES if args.quick else tuple(CASES)
    found = [n for n in names if (args.data / n).is_file()]
    if not found:
        _bench.refuse(f"{args.data}: none of {', '.join(names)} there")
    print(f"{'file':28s} {'buildings':>9s} {'seconds':>8s} {'ms/building':>12s}")
    for name in names:
        crs, path = CASES[name], args.data / name
        if name not in found:
            print(f"{name}: not found, skipped")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            state = run(path, Path(tmp) / "out", crs=parse_crs(crs) if crs else None)
            seconds, n = time_detection(state)
        print(f"{name:28s} {n:9d} {seconds:8.3f} {1000 * seconds / max(n, 1):12.1f}")


if __name__ == "__main__":
    _bench.guard(main)
