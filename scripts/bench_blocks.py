"""Benchmark: blocks split into buildings, on randomised terraced towns with known houses.

Each town (:func:`recon3d.synthetic.terraces.terraced_town` with ``mix=True``) holds
rows of attached houses whose heights mix as real terraces do (some as high as their
neighbour, most 0.5-4 m apart; flat roofs, ridges along or across the row, dormers).
Detection runs on its nDSM twice: with the split at height steps and valleys
(``split_step``, the default) and without it (only the 2 m ``split_height``); a third
row is the reference a split would reach that cut at every true step and valley and
nowhere else (houses of one height under one roof stay together: nothing in the heights
parts them). Scores against the true houses:

* one-to-one: share of houses matched by one detected building with IoU >= 0.5 (at
  that IoU a match is unique both ways);
* area completeness / correctness: share of the houses' area covered by detected
  buildings, of the detected area on houses.

Dev seeds 0-9 (tuned on) and held-out seeds 20-29 (never tuned on) are reported
apart. ``--quick``: two dev seeds.

    .venv/bin/python scripts/bench_blocks.py [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import _bench
import numpy as np
import shapely

from recon3d.buildings import detect
from recon3d.config import BuildingsConfig
from recon3d.core.geo import Units
from recon3d.synthetic.terraces import terraced_town

DEV, HELD_OUT = tuple(range(10)), tuple(range(20, 30))


def score(detected: list[shapely.Polygon], houses: list[shapely.Polygon]) -> dict[str, float]:
    """Matched houses, houses, and the areas behind completeness and correctness."""
    tree = shapely.STRtree(detected) if detected else None
    matched = 0
    for h in houses:
        if tree is None:
            break
        for j in tree.query(h, predicate="intersects"):
            d = detected[j]
            inter = d.intersection(h).area
            if inter / (d.area + h.area - inter) >= 0.5:
                matched += 1
                break
    truth, found = shapely.union_all(houses), shapely.union_all(detected) if detected else shapely.Polygon()
    overlap = truth.intersection(found).area
    return {"matched": matched, "houses": len(houses), "overlap": overlap, "truth": truth.area, "found": found.area,
            "buildings": len(detected)}


def every_true_cut(town) -> list[shapely.Polygon]:
    """The buildings of a split at every true step and valley and nowhere else: each run
    of houses nothing in the roofs parts (:attr:`~recon3d.synthetic.terraces.TerracedTown.parted`) as one."""
    runs = np.cumsum(town.parted)
    return [shapely.union_all([p for (p, _), r in zip(town.houses, runs, strict=True) if r == k])
            for k in np.unique(runs)]


def run(seeds, config: BuildingsConfig | None) -> dict[str, float]:
    """Summed scores and detection time over ``seeds``; ``config`` None: :func:`every_true_cut`."""
    total: dict[str, float] = {}
    seconds = 0.0
    for seed in seeds:
        town = terraced_town(seed, mix=True)
        start = time.perf_counter()
        if config is None:
            polygons = every_true_cut(town)
        else:
            polygons = detect.detect_buildings(town.ndsm, town.vegetation.data > 0.5, config, Units())
        seconds += time.perf_counter() - start
        for k, v in score(polygons, [p for p, _ in town.houses]).items():
            total[k] = total.get(k, 0.0) + v
    total["seconds"] = seconds
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _bench.add_quick(parser)
    args = parser.parse_args()
    dev = DEV[:2] if args.quick else DEV
    sets = {f"dev {dev[0]}-{dev[-1]}": dev}
    if not args.quick:
        sets["held-out 20-29"] = HELD_OUT
    configs = {"2 m jumps only": dataclasses.replace(BuildingsConfig(), split_step=0.0), "steps": BuildingsConfig(),
               "every true cut": None}
    print(f"{'seeds':15s} {'detection':15s} {'houses':>6s} {'buildings':>9s} {'one-to-one %':>12s} "
          f"{'complete %':>10s} {'correct %':>9s} {'ms/building':>11s}")
    for name, seeds in sets.items():
        for label, config in configs.items():
            t = run(seeds, config)
            print(f"{name:15s} {label:15s} {int(t['houses']):6d} {int(t['buildings']):9d} "
                  f"{100 * t['matched'] / t['houses']:12.1f} {100 * t['overlap'] / t['truth']:10.1f} "
                  f"{100 * t['overlap'] / max(t['found'], 1e-9):9.1f} {1000 * t['seconds'] / max(t['buildings'], 1):11.1f}")


if __name__ == "__main__":
    _bench.guard(main)
