"""Benchmark: a whole survey end to end as it grows (issue 18's targets).

A real tile (default: the Delft AHN3 strip, 208k points) is copied on a k x k grid of
shifted copies, as one LAZ for k <= 2 and as 16 LAZ files beyond (a delivery in
tiles), and ``recon3d run`` works it in a fresh process. For each size the table gives
the wall time, the time per million points, the tiles, and the peak resident memory of
the whole process tree (the run and its workers, sampled every 0.2 s with psutil), also
as PSS (shared pages counted once).

Targets: wall time at most 1.15 x linear in the points (against the 4 x survey), peak
memory within 1.25 x of the 4 x survey's whatever the area, 2 workers at least 1.7 x
faster than 1 on the 16 x survey, and a 20 M-point survey through the whole pipeline
on 2 cores in 20 minutes with at most 4 GB.

With ``--compare-workers`` a second table splits the speed-up by stage: each stage's
seconds with 1 worker and with ``--workers``, and its idle seconds (the time it takes
beyond a perfect speed-up), so the stages that hold the other cores idle stand out.

No peer runs beside it: pdal-parallelizer needs PDAL's Python binding, which no
registry here offers (bench_terrain.py times PDAL's own terrain pipeline), and no peer
builds the whole product set (DSM, DTM, classes, LoD2.2 solids) to time against.

    .venv/bin/python scripts/bench_scale.py [--sizes 1 2 4 8] [--workers 2] [--compare-workers 4] [--quick]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _bench

DATA = _bench.SHARED / "lidar" / "delft_ahn3_strip.laz"
CRS = "EPSG:7415"


def write_survey(data: Path, k: int, folder: Path, *, fraction: float = 1.0) -> tuple[list[Path], int]:
    """``data`` copied k x k times (shifted by its extent), as one file for k <= 2 and 16
    files beyond; the files and the point count. ``fraction`` keeps that share of rows."""
    import laspy
    import numpy as np

    las = laspy.read(data)
    if fraction < 1.0:
        las.points = las.points[: int(len(las.points) * fraction)]
    h = las.header
    size = (np.asarray(las.xyz).max(axis=0)[:2] - np.asarray(las.xyz).min(axis=0)[:2]) + 0.01
    split = [range(k)] if k <= 2 else np.array_split(np.arange(k), 4)  # 1 file, or 4 x 4 files
    folder.mkdir(parents=True, exist_ok=True)
    paths, total = [], 0
    for g, (rows, cols) in enumerate((a, b) for a in split for b in split):
        parts = []
        for i in rows:
            for j in cols:
                a = las.points.array.copy()
                a["X"] += int(round(i * size[0] / h.scales[0]))
                a["Y"] += int(round(j * size[1] / h.scales[1]))
                parts.append(a)
        out = laspy.LasData(laspy.LasHeader(point_format=h.point_format, version=h.version))
        out.header.scales, out.header.offsets = h.scales, h.offsets
        out.points = laspy.ScaleAwarePointRecord(np.concatenate(parts), h.point_format, h.scales, h.offsets)
        path = folder / f"part_{g:02d}.laz"
        out.write(path)
        paths.append(path)
        total += sum(len(p) for p in parts)
    return paths, total


def run_once(paths: list[Path], out: Path, workers: int, extra: list[str]) -> dict:
    """One ``recon3d run`` in a fresh process: wall time, peak RSS of its process tree, run.json."""
    import psutil

    cmd = [sys.executable, "-m", "recon3d", "-q", "run", *map(str, paths), "--crs", CRS, "-o", str(out),
           "--workers", str(workers), *extra]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    root = psutil.Process(proc.pid)
    peak = peak_pss = 0
    while proc.poll() is None:
        try:
            tree = [root, *root.children(recursive=True)]
            infos = [p.memory_full_info() for p in tree if p.is_running()]
            peak = max(peak, sum(i.rss for i in infos))
            peak_pss = max(peak_pss, sum(getattr(i, "pss", i.rss) for i in infos))
        except psutil.Error:
            pass
        time.sleep(0.2)
    wall = time.perf_counter() - start
    err = proc.stderr.read()
    if proc.returncode != 0:
        _bench.refuse(f"recon3d run failed on {paths[0].parent}: {err.strip().splitlines()[-1] if err else ''}")
    record = json.loads((out / "run.json").read_text())
    return {"wall": wall, "peak": peak, "peak_pss": peak_pss, "points": record["inputs"]["points"], "tiles": record["chosen"]["tiles"],
            "timings": record["timings_s"], "buildings": json.loads((out / "report.json").read_text())["buildings"]["count"]}


def speedup_table(single: dict[str, float], multi: dict[str, float], workers: int) -> str:
    """Per stage: seconds with 1 worker and with ``workers``, the speed-up, and the
    seconds the stage would save at a perfect speed-up (where the second core idles)."""
    lines = [f"{'stage':<22}{'1 worker s':>11}{f'{workers} workers s':>13}{'speed-up':>10}{'idle s':>8}"]
    for stage in sorted(multi, key=lambda s: -single.get(s, 0.0)):
        one, many = single.get(stage, 0.0), multi[stage]
        if max(one, many) < 0.5:
            continue
        lines.append(f"{stage:<22}{one:>11.1f}{many:>13.1f}{one / max(many, 1e-9):>10.2f}{many - one / workers:>8.1f}")
    total_one, total_many = sum(single.values()), sum(multi.values())
    lines.append(f"{'all stages':<22}{total_one:>11.1f}{total_many:>13.1f}{total_one / max(total_many, 1e-9):>10.2f}"
                 f"{total_many - total_one / workers:>8.1f}")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="the tile copied (default: the Delft strip)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 2, 4, 8], help="k of the k x k surveys")
    parser.add_argument("--workers", type=int, default=2, help="workers of the scaling runs (default: %(default)s)")
    parser.add_argument("--compare-workers", type=int, default=4, metavar="K",
                        help="also run the k x k survey (one of --sizes) with 1 worker, for the speed-up (0: not)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="passed to recon3d run --set")
    _bench.add_quick(parser)
    args = parser.parse_args()
    data = _bench.require(args.data, "LiDAR file")
    fraction, extra = 1.0, [x for o in args.overrides for x in ("--set", o)]
    if args.quick:
        args.sizes, args.compare_workers, fraction = [1, 2], 0, 0.1
        extra += ["--set", "tiles.size=32"]
    if args.compare_workers and args.compare_workers not in args.sizes:
        print(f"no 1-worker comparison: --compare-workers {args.compare_workers} is not among --sizes "
              f"{' '.join(map(str, args.sizes))}")
        args.compare_workers = 0
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in args.sizes:
            paths, n = write_survey(data, k, Path(tmp) / f"in{k}", fraction=fraction)
            rec = run_once(paths, Path(tmp) / f"out{k}", args.workers, extra)
            rows.append((k, rec))
            print(f"{k * k:>4} x: {rec['points'] / 1e6:6.2f} M points, {rec['tiles']['count']:>4} tiles of "
                  f"{rec['tiles']['size']['value']:g} m, {rec['buildings']} buildings, {rec['wall']:7.1f} s, "
                  f"peak {rec['peak'] / 2**30:5.2f} GB  stages: "
                  + ", ".join(f"{s} {v:.0f}" for s, v in rec["timings"].items() if v >= 1), flush=True)
        single = None
        if args.compare_workers:
            k = args.compare_workers
            paths, _ = write_survey(data, k, Path(tmp) / f"in{k}", fraction=fraction)
            single = run_once(paths, Path(tmp) / "single", 1, extra)
    print(f"\n{'survey':>8}{'M points':>10}{'tiles':>7}{'wall s':>9}{'s/M pts':>9}{'x linear':>10}{'peak GB':>9}{'x peak':>8}"
          f"{'PSS GB':>8}{'x PSS':>7}")
    ref = next((rec for k, rec in rows if k == 2), rows[0][1])
    for k, rec in rows:
        per = rec["wall"] / (rec["points"] / 1e6)
        linear = per / (ref["wall"] / (ref["points"] / 1e6))
        print(f"{k * k:>7}x{rec['points'] / 1e6:>10.2f}{rec['tiles']['count']:>7}{rec['wall']:>9.1f}{per:>9.1f}"
              f"{linear:>10.2f}{rec['peak'] / 2**30:>9.2f}{rec['peak'] / ref['peak']:>8.2f}"
              f"{rec['peak_pss'] / 2**30:>8.2f}{rec['peak_pss'] / ref['peak_pss']:>7.2f}")
    print("  (x linear and x peak: against the 4 x survey; targets <= 1.15 and <= 1.25. peak GB: the\n"
          "   resident memory of the run and its workers summed, as the target counts it; PSS GB: the same\n"
          "   with the pages they share (the libraries' code) counted once, what the run costs the machine)")
    if single is not None:
        multi = next(rec for k, rec in rows if k == args.compare_workers)
        print(f"\n{args.compare_workers ** 2} x survey: 1 worker {single['wall']:.1f} s, {args.workers} workers "
              f"{multi['wall']:.1f} s: {single['wall'] / multi['wall']:.2f} x faster (target >= 1.7 with 2)")
        print(speedup_table(single["timings"], multi["timings"], args.workers))
    print("peers: none run here (no peer builds the same products; PDAL's terrain part: bench_terrain.py)")
    return 0


if __name__ == "__main__":
    _bench.guard(main)
