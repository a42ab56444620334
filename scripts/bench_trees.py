"""Buildings among trees: detection and point classes on the random LiDAR family.

Each seed is a survey of :func:`recon3d.synthetic.lidar.random_survey`, written with its
true classes and CRS and run through the pipeline with default settings. The surveys
fall in four groups: no trees, trees beside buildings, trees over roofs, and groves
(clusters of touching crowns, 75 m2 and more, beside either of the other two). Per
group the table gives the surveys whose building count is exact, the area
completeness and correctness of the footprints against the true footprints (pooled
over the group, and the worst survey), the detections that lie on no building, and
the share of the true vegetation points cloud.laz labels building (pooled, worst),
and the mean area completeness and correctness against the true point classes (the
way :func:`recon3d.quality.buildings.evaluate_against_classes` scores a provider's).
``--real`` adds the shared Delft and IGN tiles against their provider's classes.

    .venv/bin/python scripts/bench_trees.py --start 0 --cases 40
    .venv/bin/python scripts/bench_trees.py --quick
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import _bench
import numpy as np

GROUPS = ("none", "beside", "over", "groves")


def group_of(spec: dict) -> str:
    """The group of a survey: its tree placement, or "groves"."""
    return "groves" if spec["city"].get("groves") else spec["city"]["trees"]


def run_case(seed: int, folder: Path) -> dict:
    """Run survey ``seed`` (with classes and CRS) and score it against its truth."""
    import shapely

    from recon3d.core.pointcloud import ASPRS
    from recon3d.pipeline.run import run
    from recon3d.quality.buildings import evaluate_footprints
    from recon3d.synthetic.lidar import random_survey, write_survey

    spec = random_survey(seed)
    spec["file"].update(classes=True, with_crs=True)
    path, city = write_survey(folder / "in", spec)
    t = time.perf_counter()
    s = run(path, folder / "out")
    seconds = time.perf_counter() - t
    doc = json.loads((folder / "out" / "buildings.city.json").read_text())
    found = sum(1 for o in doc["CityObjects"].values() if o.get("type") == "Building" and "parents" not in o)
    detected = [b.footprint for b in s.city if b.solids]
    truth = [b.footprint for b in city.buildings]
    scores = evaluate_footprints(detected, truth)
    union = shapely.union_all(truth) if truth else shapely.Polygon()
    false = sum(1 for p in detected if p.intersection(union).area < 0.5 * p.area)
    veg = s.reference_classes == ASPRS.HIGH_VEGETATION
    veg_building = int(np.count_nonzero(s.point_classes[veg] == ASPRS.BUILDING))
    true_area = sum(p.area for p in truth)
    found_area = sum(p.area for p in detected)
    overlap = shapely.union_all(detected).intersection(union).area if detected and truth else 0.0
    provider = s.report["buildings_vs_provider_area"]
    return {
        "seed": seed, "group": group_of(spec), "seconds": round(seconds, 1),
        "buildings": found, "true_buildings": len(truth), "false_detections": false,
        "true_area": round(true_area, 2), "found_area": round(found_area, 2), "overlap": round(overlap, 2),
        "completeness": scores["area_completeness"], "correctness": scores["area_correctness"],
        "vegetation_points": int(veg.sum()), "vegetation_as_building": veg_building,
        "class_completeness": provider["completeness"], "class_correctness": provider["correctness"],
    }


def summary(rows: list[dict]) -> dict:
    """Pooled figures of a group of rows."""
    if not rows:
        return {}
    true_area = sum(r["true_area"] for r in rows)
    found_area = sum(r["found_area"] for r in rows)
    overlap = sum(r["overlap"] for r in rows)
    veg = sum(r["vegetation_points"] for r in rows)
    vb = sum(r["vegetation_as_building"] for r in rows)
    per = [100.0 * r["vegetation_as_building"] / r["vegetation_points"] for r in rows if r["vegetation_points"]]
    comp = [r["completeness"] for r in rows if r["completeness"] is not None]
    corr = [r["correctness"] for r in rows if r["correctness"] is not None]
    ccomp = [r["class_completeness"] for r in rows if r["class_completeness"] is not None]
    ccorr = [r["class_correctness"] for r in rows if r["class_correctness"] is not None]
    return {
        "cases": len(rows),
        "class_completeness": round(float(np.mean(ccomp)), 1) if ccomp else None,
        "class_correctness": round(float(np.mean(ccorr)), 1) if ccorr else None,
        "count_exact": sum(r["buildings"] == r["true_buildings"] for r in rows),
        "completeness": round(100.0 * overlap / true_area, 1) if true_area else None,
        "worst_completeness": round(min(comp), 1) if comp else None,
        "correctness": round(100.0 * overlap / found_area, 1) if found_area else None,
        "worst_correctness": round(min(corr), 1) if corr else None,
        "false_detections": sum(r["false_detections"] for r in rows),
        "vegetation_as_building_percent": round(100.0 * vb / veg, 2) if veg else None,
        "worst_vegetation_percent": round(max(per), 2) if per else None,
    }


def real_tiles() -> dict:
    """The shared Delft and IGN tiles against their provider's classes (no footprints)."""
    from recon3d.core.geo import parse_crs
    from recon3d.pipeline.run import run

    data = Path(__file__).resolve().parents[2] / "shared" / "data" / "lidar"
    out = {}
    for name, file, crs in (("delft", "delft_ahn3_strip.laz", "EPSG:7415"), ("ign", "ign_village_2154.laz", None)):
        with tempfile.TemporaryDirectory() as tmp:
            s = run(data / file, Path(tmp) / "out", crs=parse_crs(crs) if crs else None)
        r = s.report["buildings_vs_provider_area"]
        out[name] = {k: r.get(k) for k in ("completeness", "correctness", "vegetation_points", "vegetation_as_building_percent",
                                         "object_completeness", "object_correctness")}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--start", type=int, default=0, help="first seed")
    parser.add_argument("--cases", type=int, default=40)
    parser.add_argument("--seeds", type=int, nargs="+", help="these seeds instead of --start/--cases")
    parser.add_argument("--real", action="store_true", help="also the shared real tiles")
    _bench.add_quick(parser)  # two seeds only
    parser.add_argument("--json", type=Path, help="write every row here")
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    seeds = [8, 5] if args.quick else args.seeds or list(range(args.start, args.start + args.cases))
    rows = []
    print(f"{'seed':>5} {'group':>7} {'s':>6} {'bldg':>6} {'false':>5} {'compl':>6} {'corr':>6} {'veg->bldg %':>11}")
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            r = run_case(seed, Path(tmp))
        rows.append(r)
        pct = 100.0 * r["vegetation_as_building"] / r["vegetation_points"] if r["vegetation_points"] else float("nan")
        fmt = lambda v: f"{v:6.1f}" if v is not None else f"{'-':>6}"  # noqa: E731
        print(f"{seed:5d} {r['group']:>7} {r['seconds']:6.1f} {r['buildings']:>3}/{r['true_buildings']:<2} "
              f"{r['false_detections']:5d} {fmt(r['completeness'])} {fmt(r['correctness'])} {pct:11.2f}", flush=True)
    print(f"\n{'group':>7} {'exact':>7} {'compl':>6} {'worst':>6} {'corr':>6} {'worst':>6} {'false':>5} {'veg %':>6} {'worst':>6} {'c.cmp':>6} {'c.cor':>6}")
    table = {}
    for g in GROUPS:
        s = summary([r for r in rows if r["group"] == g])
        table[g] = s
        if s:
            print(f"{g:>7} {s['count_exact']:>3}/{s['cases']:<3} {s['completeness']!s:>6} {s['worst_completeness']!s:>6} "
                  f"{s['correctness']!s:>6} {s['worst_correctness']!s:>6} {s['false_detections']:5d} "
                  f"{s['vegetation_as_building_percent']!s:>6} {s['worst_vegetation_percent']!s:>6} "
                  f"{s['class_completeness']!s:>6} {s['class_correctness']!s:>6}")
    result = {"rows": rows, "groups": table}
    if args.real:
        result["real"] = real_tiles()
        for name, r in result["real"].items():
            print(f"{name}: {r}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    sys.exit(0)


if __name__ == "__main__":
    main()
