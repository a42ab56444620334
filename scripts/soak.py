"""Soak test: many small random LiDAR surveys run end to end through the command line.

Each case is a survey of :func:`recon3d.synthetic.lidar.random_survey` (terrain,
layout, trees, density, noise, CRS, LAS or LAZ, with or without classes and CRS,
heights offset up to 2500 m); one case in four is then damaged (truncated, cut to a
few points, bytes flipped). ``recon3d run`` must either publish every product, or
refuse with one line naming the file, exit 1 and nothing written, and never leave a
traceback or a work folder behind. Valid cases are also scored against the truth:
DTM RMS at the ground check points, buildings found.

    .venv/bin/python scripts/soak.py              # 50 cases
    .venv/bin/python scripts/soak.py --cases 200 --start 1000
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: Products every successful LiDAR run publishes.
PRODUCTS = ("dsm.tif", "dtm.tif", "ndsm.tif", "model_dsm.tif", "cloud.laz", "buildings.city.json", "buildings.obj",
            "buildings.glb", "buildings_3dtiles/tileset.json", "footprints.geojson", "footprints.gpkg", "report.json",
            "run.json")

DAMAGES = ("truncated", "few_points", "flipped")


def make_case(seed: int, folder: Path) -> dict:
    """Write case ``seed`` into ``folder``: the survey, damaged for one seed in four."""
    from recon3d.synthetic.city import checkpoints
    from recon3d.synthetic.lidar import random_survey, write_survey

    spec = random_survey(seed)
    path, city = write_survey(folder, spec)
    rng = np.random.default_rng([seed, 99])
    damage = str(rng.choice(DAMAGES)) if rng.uniform() < 0.25 else None
    if damage == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * rng.uniform(0.2, 0.9))])
    elif damage == "few_points":
        import laspy

        las = laspy.read(path)
        las.points = las.points[: int(rng.integers(1, 60))]
        las.write(path)
    elif damage == "flipped":
        data = bytearray(path.read_bytes())
        for i in rng.integers(0, min(len(data), 400), 6):  # the header and the first records
            data[i] ^= 0xFF
        path.write_bytes(bytes(data))
    xyz, _, kinds = checkpoints(city)
    truth = {"ground": xyz[np.asarray(kinds) == "ground"].tolist(), "buildings": len(city.buildings)}
    return {"seed": seed, "path": path, "spec": spec, "damage": damage, "truth": truth}


def run_case(case: dict, out: Path, timeout: float = 600.0) -> dict:
    """Run ``recon3d run`` on a case and check what it left; ``problems`` lists every breach."""
    args = [sys.executable, "-m", "recon3d", "-q", "run", str(case["path"]), "-o", str(out)]
    if not case["spec"]["file"]["with_crs"]:
        args += ["--crs", case["spec"]["city"]["crs"]]
    before = sorted(p.name for p in out.parent.iterdir())
    t = time.perf_counter()
    result = subprocess.run(args, capture_output=True, text=True, timeout=timeout, cwd=out.parent)
    row = {"seed": case["seed"], "damage": case["damage"], "exit": result.returncode,
           "seconds": round(time.perf_counter() - t, 1), "problems": []}
    problems = row["problems"]
    if "Traceback" in result.stderr:
        problems.append("traceback: " + result.stderr.strip().splitlines()[-1][:200])
    left = sorted(set(p.name for p in out.parent.iterdir()) - set(before) - {out.name})
    if left:
        problems.append(f"left behind: {left}")
    if result.returncode == 1:
        lines = result.stderr.strip().splitlines()
        row["error"] = lines[0][:160] if lines else ""
        if len(lines) != 1 or not lines[0].startswith("recon3d: error: ") or case["path"].name not in lines[0]:
            problems.append(f"not one line naming the file: {result.stderr.strip()[:300]!r}")
        if out.exists():
            problems.append("refused, yet the output folder exists")
        if case["damage"] is None:
            problems.append(f"a valid survey refused: {row['error']}")
    elif result.returncode == 0:
        missing = [p for p in PRODUCTS if not (out / p).exists()]
        if missing:
            problems.append(f"products missing: {missing}")
        else:
            row.update(_score(case, out))
    else:
        problems.append(f"exit {result.returncode}: {result.stderr.strip()[-300:]!r}")
    return row


def _score(case: dict, out: Path) -> dict:
    """DTM RMS at the ground check points and the buildings found, against the truth."""
    import laspy

    from recon3d.io.geotiff import read_raster

    ground = np.asarray(case["truth"]["ground"])
    dtm = read_raster(out / "dtm.tif")
    e = dtm.sample(ground[:, 0], ground[:, 1]) - ground[:, 2]
    e = e[np.isfinite(e)]
    city = json.loads((out / "buildings.city.json").read_text())
    found = sum(1 for o in city["CityObjects"].values() if o.get("type") == "Building" and "parents" not in o)
    with laspy.open(out / "cloud.laz") as f:
        points = f.header.point_count
    return {"dtm_rms": round(float(np.sqrt(np.mean(e**2))), 3) if e.size else None, "ground_checks": int(e.size),
            "buildings": found, "true_buildings": case["truth"]["buildings"], "points": points}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=50)
    parser.add_argument("--start", type=int, default=0, help="first seed")
    parser.add_argument("--json", type=Path, help="write every row here")
    args = parser.parse_args()
    rows = []
    print(f"{'seed':>5} {'damage':>11} {'exit':>4} {'s':>6} {'DTM RMS':>8} {'bldg':>9}  problems / error")
    for seed in range(args.start, args.start + args.cases):
        with tempfile.TemporaryDirectory() as tmp:
            case = make_case(seed, Path(tmp) / "in")
            (Path(tmp) / "work").mkdir()
            row = run_case(case, Path(tmp) / "work" / "out")
        rows.append(row)
        rms = f"{row['dtm_rms']:8.3f}" if row.get("dtm_rms") is not None else f"{'-':>8}"
        bldg = f"{row['buildings']}/{row['true_buildings']}" if "buildings" in row else "-"
        print(f"{seed:5d} {row['damage'] or '-':>11} {row['exit']:4d} {row['seconds']:6.1f} {rms} {bldg:>9}  "
              f"{'; '.join(row['problems']) or row.get('error', '')}", flush=True)
    bad = [r for r in rows if r["problems"]]
    valid = [r["dtm_rms"] for r in rows if r.get("dtm_rms") is not None]
    print(f"\n{len(rows)} cases, {len(bad)} with problems; {sum(r['exit'] == 0 for r in rows)} published, "
          f"{sum(r['exit'] == 1 for r in rows)} refused; DTM RMS median {np.median(valid):.3f} m, "
          f"max {np.max(valid):.3f} m over {len(valid)} published" if valid else "")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
