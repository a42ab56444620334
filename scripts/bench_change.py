"""Benchmark of recon3d.quality.change.detect_changes on a synthetic town.

Usage: python scripts/bench_change.py [n_buildings] [--quick]

Builds n square-ish buildings on a 0.5 m nDSM, shifts the new outlines by 0.7 m,
splits every 10th old building in two, removes every 15th new one (demolished)
and adds new ones, then reports buildings compared per second. ``--quick``: 100
buildings.
"""

from __future__ import annotations

import argparse
import sys
import time

import _bench
import numpy as np
import shapely
import shapely.affinity
from affine import Affine

from recon3d.core.city import Building, CityModel
from recon3d.core.raster import Raster
from recon3d.io.vectors import Footprint
from recon3d.quality.change import detect_changes


def town(n: int, seed: int = 0):
    """Old footprints, new city model and nDSM of ``n`` buildings on a 20 m lattice."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    res, size = 0.5, side * 20.0 + 20
    x0, y0 = 500000.0, 5000000.0
    ndsm = np.zeros((int(size / res), int(size / res)), np.float32)
    grid = Raster(ndsm, Affine(res, 0, x0, 0, -res, y0 + size))
    old, new = [], []
    for k in range(n):
        i, j = divmod(k, side)
        w, h = rng.uniform(8, 14), rng.uniform(8, 14)
        x, y = x0 + 10 + j * 20, y0 + 10 + i * 20
        height = rng.uniform(4, 12)
        poly = shapely.box(x, y, x + w, y + h)
        if k % 10 == 0:
            attrs = {"roof_z": 100 + height}
            old += [
                Footprint(f"o{k}a", shapely.box(x, y, x + w / 2, y + h), attrs),
                Footprint(f"o{k}b", shapely.box(x + w / 2, y, x + w, y + h), attrs),
            ]
        elif k % 17 != 0:  # every 17th: new building
            old.append(Footprint(f"o{k}", poly, {"roof_z": 100 + height}))
        if k % 15 == 0:  # demolished: no new building, flat nDSM
            continue
        moved = shapely.affinity.translate(poly, 0.7, 0.0)
        new.append(Building(f"n{k}", moved, 100.0, 100 + height))
        r0, c0 = int((y0 + size - (y + h)) / res), int((x + 0.7 - x0) / res)
        grid.data[r0 : r0 + int(h / res), c0 : c0 + int(w / res)] = height
    return old, CityModel(new, None), grid


QUICK_BUILDINGS = 100


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("n", nargs="?", type=int, default=5000, help="buildings in the town (default: %(default)s)")
    _bench.add_quick(parser)
    args = parser.parse_args()
    n = QUICK_BUILDINGS if args.quick else args.n
    if n < 1:
        _bench.refuse(f"{n} buildings: at least 1 is needed")
    old, city, ndsm = town(n)
    t = time.perf_counter()
    result = detect_changes(old, city, ndsm)
    dt = time.perf_counter() - t
    compared = len(old) + len(city.buildings)
    sys.stdout.write(
        f"{len(old)} old + {len(city.buildings)} new buildings in {dt:.2f} s: "
        f"{len(old) / dt:.0f} old buildings/s ({compared / dt:.0f} outlines/s)\n{result.summary}\n"
    )


if __name__ == "__main__":
    _bench.guard(main)
