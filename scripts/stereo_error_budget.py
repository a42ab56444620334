"""Where the stereo DSM's error comes from: the matcher, or the stages after it.

Runs `recon3d run` on a rendered city twice: once with the dense matcher, once with
the exact disparities ray-cast from the city (a perfect matcher, occlusions
included). Both DSMs are compared with the truth inside the area two images see, a
height anywhere between the lowest and highest truth surface within the cell counting
as exact (:func:`recon3d.synthetic.score.truth_range`), and the squared error is split
by kind of place: roof interiors (more than 1 m inside an outline), the band of +-1 m
around outlines (inside and outside the footprint), tree crowns and open ground. A
second table splits it by what the data holds at each cell: whether two cameras see
its top surface unhidden (so stereo can measure it), whether a matched point fell in
it or it was filled, and, for filled cells two cameras see, how steep the true
surface is there (roof faces foreshortened in one view are the usual unmatched ones).

    .venv/bin/python scripts/stereo_error_budget.py [--scene DIR | --seed 0 | --survey nadir_pair --width 800]

A DSM error the perfect matcher shares is not the matcher's: it comes from
triangulation, fusion and outlier removal, gridding (highest point per cell against
a truth sampled at cell centres) and hole filling (ground neither image sees).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import tempfile
from pathlib import Path
from unittest import mock

import numpy as np
import rasterio.features
import shapely

from recon3d.io.geotiff import read_raster
from recon3d.pipeline.run import run
from recon3d.synthetic import write_scene
from recon3d.synthetic.city import truth_disparity
from recon3d.synthetic.family import CONFIGURATIONS
from recon3d.synthetic.scene import scene_city, write_block_scene
from recon3d.synthetic.score import _on_grid, tolerant_error, truth_range, visible_cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, help="a scene folder written by recon3d.synthetic (default: render one)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the rendered demo city (without --scene)")
    parser.add_argument("--survey", choices=sorted(CONFIGURATIONS), help="a named survey of the family instead")
    parser.add_argument("--width", type=int, help="image width of the survey (same geometry)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scene = args.scene
        if scene is None:
            scene = Path(tmp) / "scene"
            if args.survey:
                spec = CONFIGURATIONS[args.survey]
                write_block_scene(scene, spec.with_width(args.width) if args.width else spec)
            else:
                write_scene(scene, seed=args.seed)
        city = scene_city(scene)
        places = _places(scene)
        rows, evidence = {}, {}
        for name, perfect in (("matcher", False), ("perfect disparities", True)):
            out = Path(tmp) / name.replace(" ", "_")
            with _perfect_matcher(scene, city) if perfect else contextlib.nullcontext():
                state = run(scene, out)
            common = _on_grid(read_raster(scene / "truth" / "views.tif"), state.dsm) >= 2
            rows[name] = _budget(state.dsm, city, common, places(state.dsm))
            evidence[name] = _budget(state.dsm, city, common, _evidence(scene, city, state, common))
    _print(rows, "DSM - truth (tolerant)")
    print()
    _print(evidence, "by evidence")


def _perfect_matcher(scene: Path, city):
    """Patch triangulation to use the ray-cast disparity wherever the matcher gave one."""
    from recon3d.io.colmap import read_scene
    from recon3d.stereo import triangulate as tri

    offset = read_scene(scene).offset
    original = tri.triangulate

    def exact(pair, disparity, confidence, **kw):
        truth = truth_disparity(city, pair, offset)
        truth[~np.isfinite(disparity)] = np.nan  # same footprint: nodata borders stay out
        kw["guessed"] = None
        return original(pair, truth, np.isfinite(truth).astype(np.float32), **kw)

    return mock.patch("recon3d.pipeline.stereo.triangulate", exact)


def _places(scene: Path):
    """A function giving, on a DSM grid, the (rows, cols) bool mask of each kind of place."""
    doc = json.loads((scene / "truth" / "footprints.geojson").read_text())
    outlines = [shapely.geometry.shape(f["geometry"]) for f in doc["features"]]
    with open(scene / "truth" / "trees.csv", newline="") as f:
        crowns = [shapely.Point(float(r["x"]), float(r["y"])).buffer(float(r["crown_radius"]) + 0.5) for r in csv.DictReader(f)]

    def masks(grid) -> dict[str, np.ndarray]:
        def burn(geoms):
            geoms = [g for g in geoms if not g.is_empty]
            if not geoms:
                return np.zeros(grid.shape, bool)
            return rasterio.features.rasterize([(g, 1) for g in geoms], out_shape=grid.shape, transform=grid.transform).astype(bool)

        inner = burn([p.buffer(-1.0) for p in outlines])
        inside = burn(outlines)
        band = burn([p.buffer(1.0) for p in outlines]) & ~inner
        trees = burn(crowns)
        return {
            "roof interior": inner & ~trees,
            "outline band, inside": band & inside & ~trees,
            "outline band, outside": band & ~inside & ~trees,
            "tree crowns": trees,
            "open ground": ~inner & ~band & ~trees,
        }

    return masks


#: Slopes (degrees) splitting the filled cells two cameras see: flat ground and roofs,
#: roof faces, and steeper (walls crossing the cell).
SLOPES = (20.0, 50.0)


def _evidence(scene: Path, city, state, common: np.ndarray) -> dict[str, np.ndarray]:
    """(rows, cols) bool masks of the DSM cells by what the run had there: two views of
    the top surface or one, a matched point or a filled value (and, for filled cells
    both see, the true surface's slope)."""
    dsm = state.dsm
    matched = ~state.dsm_filled & np.isfinite(dsm.data)
    if state.dsm_unobserved is not None:
        matched &= ~state.dsm_unobserved
    both = visible_cells(scene, city, dsm, common)
    _, top = truth_range(city, dsm, common, samples=1)
    gy, gx = np.gradient(np.nan_to_num(top, nan=float(np.nanmedian(top))), dsm.resolution)
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    flat, steep = slope < SLOPES[0], slope >= SLOPES[1]
    seen_filled = both & ~matched
    return {
        "two views, matched": both & matched,
        f"two views, filled, < {SLOPES[0]:g} deg": seen_filled & flat,
        f"two views, filled, {SLOPES[0]:g}-{SLOPES[1]:g} deg": seen_filled & ~flat & ~steep,
        f"two views, filled, >= {SLOPES[1]:g} deg": seen_filled & steep,
        "one view, matched": ~both & matched,
        "one view, filled": ~both & ~matched,
    }


def _budget(dsm, city, common, places: dict[str, np.ndarray]) -> dict:
    error = tolerant_error(city, dsm, common)
    valid = np.isfinite(error)
    total = float(np.sum(error[valid] ** 2))
    out = {"all": (int(valid.sum()), float(np.sqrt(total / valid.sum())), 100.0)}
    for name, mask in places.items():
        e = error[mask & valid]
        out[name] = (e.size, float(np.sqrt(np.mean(e**2))) if e.size else float("nan"), 100.0 * float(np.sum(e**2)) / total)
    return out


def _print(rows: dict, title: str) -> None:
    names = list(rows)
    print(f"{title:34s}" + "".join(f"{n:>34s}" for n in names))
    print(f"{'':34s}" + "".join(f"{'cells':>10s}{'RMS (m)':>10s}{'% of MSE':>14s}" for _ in names))
    for place in rows[names[0]]:
        line = f"{place:34s}"
        for n in names:
            cells, rms, share = rows[n][place]
            line += f"{cells:10d}{rms:10.2f}{share:14.1f}"
        print(line)


if __name__ == "__main__":
    main()
