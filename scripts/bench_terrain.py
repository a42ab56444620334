"""Benchmark: DSM + ground filter + DTM + nDSM throughput (points per second).

The Delft AHN3 strip is repeated on a k x k grid of shifted copies to get a cloud of
realistic density and a few million points, then each terrain stage is timed.

    .venv/bin/python scripts/bench_terrain.py [--copies 4]
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np

from recon3d.config import GroundConfig
from recon3d.core.geo import crs_units, parse_crs
from recon3d.core.pointcloud import PointCloud
from recon3d.io.las import read_las
from recon3d.terrain import dsm, dtm, ground

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "lidar" / "delft_ahn3_strip.laz"


def tiled_cloud(copies: int) -> PointCloud:
    base = read_las(DATA, crs=parse_crs("EPSG:7415"))
    lo, hi = base.bounds
    size = hi[:2] - lo[:2]
    parts, attrs = [], {k: [] for k in base.attributes}
    for i in range(copies):
        for j in range(copies):
            parts.append(base.xyz + [i * size[0], j * size[1], 0.0])
            for k, v in base.attributes.items():
                attrs[k].append(v)
    return PointCloud(np.concatenate(parts), {k: np.concatenate(v) for k, v in attrs.items()}, base.crs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=4, help="k for a k x k tiling of the strip")
    args = parser.parse_args()
    cloud = tiled_cloud(args.copies)
    units = crs_units(cloud.crs)
    n = len(cloud)
    times = {}
    t = time.perf_counter()
    spacing = dsm.point_spacing(cloud.xyz[:, :2])
    res, _ = dsm.choose_resolution(spacing, units)
    surface = dsm.make_dsm(cloud, res, max_hole_cells=int(25 / res**2))
    times["dsm"] = time.perf_counter() - t
    t = time.perf_counter()
    result = ground.classify_ground(cloud, GroundConfig(), units, res)
    times["ground"] = time.perf_counter() - t
    t = time.perf_counter()
    terrain = dtm.make_dtm(cloud.xyz[result.is_ground], surface)
    dtm.make_ndsm(surface, terrain)
    times["dtm+ndsm"] = time.perf_counter() - t
    total = sum(times.values())
    print(f"{n:,} points, grid {surface.shape[0]} x {surface.shape[1]} at {res} m")
    for name, s in times.items():
        print(f"  {name:<9} {s:6.2f} s  {n / s / 1e6:6.2f} M points/s")
    print(f"  {'total':<9} {total:6.2f} s  {n / total / 1e6:6.2f} M points/s")
    print(f"  peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
