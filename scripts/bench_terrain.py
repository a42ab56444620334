"""Benchmark: DSM + ground filter + DTM + nDSM throughput (points per second).

The Delft AHN3 strip is repeated on a k x k grid of shifted copies to get a cloud of
realistic density and a few million points, then each terrain stage is timed.

``--quick``: one copy of the strip (208k points).

    .venv/bin/python scripts/bench_terrain.py [--copies 4] [--data FILE] [--quick]
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import _bench
import numpy as np

from recon3d.config import GroundConfig
from recon3d.core.geo import crs_units, parse_crs
from recon3d.core.pointcloud import PointCloud
from recon3d.io.las import read_las
from recon3d.pipeline.run import HOLE_AREA
from recon3d.terrain import dsm, dtm, ground

DATA = _bench.SHARED / "lidar" / "delft_ahn3_strip.laz"
CRS = "EPSG:7415"  # the Delft strip's, not in its header; a file with its own CRS keeps it


def tiled_cloud(copies: int, data: Path = DATA) -> PointCloud:
    base = read_las(data, crs=parse_crs(CRS) if data.name == DATA.name else None)
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
    parser.add_argument("--data", type=Path, default=DATA, help="LAS/LAZ file to tile (default: %(default)s)")
    _bench.add_quick(parser)
    args = parser.parse_args()
    if args.quick:
        args.copies = 1
    if args.copies < 1:
        _bench.refuse(f"--copies {args.copies}: at least 1")
    cloud = tiled_cloud(args.copies, _bench.require(args.data, "LiDAR file"))
    units = crs_units(cloud.crs)
    n = len(cloud)
    times = {}
    t = time.perf_counter()
    spacing = dsm.point_spacing(cloud.xyz[:, :2])
    res, _ = dsm.choose_resolution(spacing, units)
    surface = dsm.make_dsm(cloud, res, max_hole_cells=int(HOLE_AREA["lidar"][0] / res**2))
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
    _bench.guard(main)
