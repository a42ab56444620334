"""Benchmark: building outlines from the nDSM against outlines refined from the images.

For surveys of :mod:`recon3d.synthetic.family` (rendered at ``--width`` pixels, the
survey's GSD kept), runs ``recon3d run`` with ``buildings.image_outlines=false``, then
:func:`recon3d.buildings.image_outline.refine_outlines` on the same outlines, DSM and
images (the call the pipeline makes by default), and scores both outlines of every
detected building against its true footprint (IoU >= 0.5): the RMS distance of the
true outline, sampled every 10 cm, to the detected one (samples over 3 m off left out,
as ``recon3d evaluate buildings`` scores outlines). Per survey and pooled: the median and
RMS of that distance, and the share of buildings the images made better / worse (by
more than 1 cm).

    .venv/bin/python scripts/bench_image_outlines.py --start 20 --random 4
    .venv/bin/python scripts/bench_image_outlines.py --named nadir_pair,heading_90 --random 0
    .venv/bin/python scripts/bench_image_outlines.py --quick
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import _bench
import numpy as np
import shapely

from recon3d.buildings.image_outline import refine_outlines
from recon3d.config import PipelineConfig
from recon3d.pipeline.run import run
from recon3d.quality.buildings import evaluate_footprints
from recon3d.stereo.ortho import frame_views
from recon3d.synthetic.family import CONFIGURATIONS, random_spec
from recon3d.synthetic.scene import write_block_scene


def outline_rms(polygon: shapely.Polygon, truth: shapely.Polygon) -> float:
    """RMS distance of the true outline, sampled every 10 cm, to ``polygon``'s
    (:func:`~recon3d.quality.buildings.evaluate_footprints`, as ``recon3d evaluate buildings``)."""
    return evaluate_footprints([polygon], [truth], step=0.1, overlap=0.0)["outline_rms"]


def matched(polygon: shapely.Polygon, truth: list, tree: shapely.STRtree) -> shapely.Polygon | None:
    """The true footprint with the highest IoU (>= 0.5) with ``polygon``."""
    best, iou = None, 0.5
    for k in tree.query(polygon):
        t = truth[k]
        value = t.intersection(polygon).area / t.union(polygon).area
        if value >= iou:
            best, iou = t, value
    return best


def bench_one(spec, tmp: Path) -> dict:
    folder = tmp / spec.name
    write_block_scene(folder, spec)
    config = PipelineConfig().with_overrides(["buildings.image_outlines=false"])
    state = run(folder, tmp / f"out-{spec.name}", overwrite=True, config=config)
    polygons = [b.footprint for b in state.city]
    refined = refine_outlines(polygons, frame_views(state.scene), state.dsm, metre=state.units.length(1.0))
    features = json.loads((folder / "truth" / "footprints.geojson").read_text())["features"]
    truth = [shapely.geometry.shape(f["geometry"]) for f in features]
    tree = shapely.STRtree(truth)
    pairs = [(outline_rms(p, t), outline_rms(r.polygon, t))
             for p, r in zip(polygons, refined, strict=True) if (t := matched(p, truth, tree)) is not None]
    pairs = [e for e in pairs if None not in e]  # every sample of the true outline over 3 m off
    return {"scene": spec.name, "gsd": spec.gsd, "buildings": len(polygons), "errors": pairs,
            "moved": sum(r.source == "images" for r in refined)}


def summary(name: str, errors: list, moved: int, buildings: int) -> str:
    e = np.asarray(errors).reshape(-1, 2)
    if not len(e):
        return f"{name:16s} no building matched"
    ndsm, image = e[:, 0], e[:, 1]
    better, worse = np.mean(image < ndsm - 0.01), np.mean(image > ndsm + 0.01)
    return (f"{name:16s} {len(e):5d} {moved:4d}/{buildings:<4d} {np.median(ndsm):7.3f} {np.sqrt(np.mean(ndsm**2)):7.3f}"
            f" {np.median(image):7.3f} {np.sqrt(np.mean(image**2)):7.3f} {100 * better:7.0f} {100 * worse:6.0f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--named", default="nadir_pair,heading_90,wide_base", help="named configurations (comma-separated)")
    parser.add_argument("--random", type=int, default=4, help="random surveys")
    parser.add_argument("--start", type=int, default=20, help="seed of the first random survey")
    parser.add_argument("--width", type=int, default=1200, help="image width (px); the survey's GSD is kept")
    parser.add_argument("--json", type=Path, help="write every figure here")
    _bench.add_quick(parser)
    args = parser.parse_args()
    names = [n for n in args.named.split(",") if n]
    unknown = [n for n in names if n not in CONFIGURATIONS]
    if unknown:
        _bench.refuse(f"{', '.join(unknown)}: not a named configuration ({', '.join(CONFIGURATIONS)})")
    specs = [CONFIGURATIONS[n] for n in names] + [random_spec(args.start + k) for k in range(args.random)]
    width = args.width
    if args.quick:
        specs, width = [CONFIGURATIONS["nadir_pair"]], 400
    specs = [s.with_width(min(width, s.width)) for s in specs]
    rows = []
    print(f"{'survey':16s} {'n':>5s} {'moved':>9s} {'nDSM med':>7s} {'rms':>7s} {'image med':>7s} {'rms':>7s} {'better%':>7s} {'worse%':>6s}")
    with tempfile.TemporaryDirectory() as tmp:
        for spec in specs:
            row = bench_one(spec, Path(tmp))
            rows.append(row)
            print(summary(row["scene"], row["errors"], row["moved"], row["buildings"]), flush=True)
    pooled = [e for r in rows for e in r["errors"]]
    print(summary("pooled", pooled, sum(r["moved"] for r in rows), sum(r["buildings"] for r in rows)))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
