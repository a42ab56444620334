"""Benchmark: a rendered 2000 x 1500 aerial pair to a fused point cloud (rectify, match, triangulate, fuse).

    .venv/bin/python scripts/bench_stereo.py [--width 2000 --height 1500]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

from recon3d.config import StereoConfig
from recon3d.io.colmap import read_scene
from recon3d.pipeline.stereo import dense_cloud
from recon3d.synthetic import write_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=2000)
    parser.add_argument("--height", type=int, default=1500)
    parser.add_argument("--gsd", type=float, default=0.1, help="ground sample distance (m)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "scene"
        size = 0.75 * args.gsd * min(args.width, args.height)
        t = time.perf_counter()
        write_scene(folder, seed=0, size=size, gsd=args.gsd, image_size=(args.width, args.height))
        render = time.perf_counter() - t
        scene = read_scene(folder)
        t = time.perf_counter()
        cloud, report = dense_cloud(scene, StereoConfig())
        seconds = time.perf_counter() - t
    pair = report["pairs"][0]
    print(f"{args.width} x {args.height} pair, {size:.0f} m city at {args.gsd} m GSD (render {render:.1f} s)")
    print(f"  disparity range {pair['disparity_range']['value']}, vertical parallax {pair['vertical_parallax_px']}")
    print(f"  pair to fused cloud: {seconds:.1f} s, {len(cloud):,} points")
    print(f"  peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
