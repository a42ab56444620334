"""Benchmark: one 2000 x 1500 aerial pair to a fused point cloud (rectify, match, triangulate, self-check, fuse).

Renders the survey ``nadir_pair`` of the family (or another, ``--survey``), then times
:func:`recon3d.pipeline.stereo.dense_cloud` on it and reports the stages of the matcher
and the peak memory.

``--quick``: the same survey at 320 px wide.

    .venv/bin/python scripts/bench_stereo.py [--survey nadir_pair] [--width 2000] [--engine census] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import tempfile
import time
from pathlib import Path

import _bench

from recon3d.config import StereoConfig
from recon3d.io.colmap import read_scene
from recon3d.pipeline.stereo import dense_cloud
from recon3d.synthetic.family import CONFIGURATIONS
from recon3d.synthetic.scene import write_block_scene

QUICK_WIDTH = 320  # px
MIN_WIDTH = 64  # px: below, the pair holds too few pixels to match


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--survey", default="nadir_pair", choices=sorted(CONFIGURATIONS))
    parser.add_argument("--width", type=int, help="image width (default: the survey's, 2000 px for nadir_pair)")
    parser.add_argument("--engine", default="census", choices=["census", "sgbm"])
    _bench.add_quick(parser)
    args = parser.parse_args()
    if args.quick:
        args.width = QUICK_WIDTH
    if args.width is not None and args.width < MIN_WIDTH:
        _bench.refuse(f"--width {args.width}: images of at least {MIN_WIDTH} px are needed")
    spec = CONFIGURATIONS[args.survey]
    if args.width:
        spec = spec.with_width(args.width)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "scene"
        t = time.perf_counter()
        write_block_scene(folder, spec)
        render = time.perf_counter() - t
        scene = read_scene(folder)
        t = time.perf_counter()
        cloud, report = dense_cloud(scene, dataclasses.replace(StereoConfig(), engine=args.engine))
        seconds = time.perf_counter() - t
    print(f"{args.survey}: {spec.strips * spec.images_per_strip} images of {spec.width} x {spec.height} px (render {render:.1f} s)")
    for pair in report["pairs"]:
        m = pair["matching"]
        print(f"  {pair['pair']}: rectified {pair['rectified_size']}, disparities {pair['disparity_range']['value']}, "
              f"matched {pair['matched_percent']} % of the overlap, matcher {m['seconds']}")
    print(f"  {len(report['pairs'])} pair(s) to fused cloud: {seconds:.1f} s, {len(cloud):,} points")
    print(f"  peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    _bench.guard(main)
