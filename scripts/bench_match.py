"""Benchmark of the dense matcher (recon3d.stereo.match): time, throughput, memory, accuracy.

Cases, each run in its own subprocess so that the peak RSS (resource.getrusage) is its own:

* ``cones``: Middlebury 2003 cones (../shared/data/stereo/middlebury_cones), disparities
  0..64; bad-1 / bad-2 (% of non-occluded pixels with a ground truth whose error exceeds
  1 / 2 px, invalid pixels counted as errors), mean absolute error over valid pixels,
  density. Also the raw OpenCV StereoSGBM baseline with typical parameters.
* ``synthetic``: a 2000 x 1500 random-texture pair of a sloping ground (disparity 20..60)
  with three box "buildings" (70, 90, 110 px), searched over 128 disparities (0..128);
  the same accuracy figures against its exact ground truth (occluded pixels excluded).
* ``large``: the same kind of pair, 1800 x 1500 px, whose ground slopes from 10 to 200 px
  of disparity with buildings up to 240 px, searched over 256 disparities (0..256): a
  scene that fills the range, so that no coarse pass can narrow it.

The peers are OpenCV's StereoSGBM in its three modes, as usually configured: ``raw-sgbm``
(MODE_SGBM, 5 directions), ``raw-sgbm-hh`` (MODE_HH, 8 directions, full-image buffers)
and ``raw-sgbm-3way`` (MODE_SGBM_3WAY, multithreaded). Each recon3d engine is printed
beside each of them with the ratio. ``--quick``: the cones case alone (450 x 375 px).
A case that fails makes the benchmark exit 1.

Usage::

    .venv/bin/python scripts/bench_match.py                 # everything
    .venv/bin/python scripts/bench_match.py --case cones --engine census
    .venv/bin/python scripts/bench_match.py --case large
    .venv/bin/python scripts/bench_match.py --quick [--data DIR]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
import warnings
from pathlib import Path

import _bench
import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CONES = _bench.SHARED / "stereo" / "middlebury_cones"
CONES_FILES = ("left.png", "right.png", "disp_left.tif", "occlusion.png")


def load_cones(data: Path = CONES):
    import rasterio

    left = cv2.imread(str(data / "left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(data / "right.png"), cv2.IMREAD_GRAYSCALE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(data / "disp_left.tif") as src:
            gt = src.read(1).astype(np.float32)
    occlusion = cv2.imread(str(data / "occlusion.png"), cv2.IMREAD_GRAYSCALE)
    if left is None or right is None or occlusion is None:
        _bench.refuse(f"{data}: unreadable Middlebury cones images ({', '.join(CONES_FILES)})")
    mask = (gt > 0) & (occlusion == 255)  # white = non-occluded; gt 0 = unknown
    return left, right, gt, mask, (0, 64)


#: Synthetic cases: (rows, cols, ground disparity at the top and bottom, boxes (row, col,
#: rows, cols, disparity), searched range).
SYNTHETIC = {
    "synthetic": (1500, 2000, (20.0, 60.0), ((200, 300, 300, 400, 90), (800, 1200, 400, 300, 110), (1000, 200, 200, 600, 70)), (0, 128)),
    "large": (1500, 1800, (10.0, 200.0), ((200, 300, 300, 400, 150), (800, 1100, 400, 300, 240), (1000, 200, 200, 600, 220)), (0, 256)),
}


def synthetic_pair(case: str = "synthetic", seed: int = 0):
    """Textured pair from a right-image disparity map; left ground truth by z-buffered splat."""
    h, w, (top, bottom), boxes, searched = SYNTHETIC[case]
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.2)
    tex += 0.5 * cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 6.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    disp_right = top + (bottom - top) * yy / h
    for y0, x0, bh, bw, d in boxes:
        disp_right[y0 : y0 + bh, x0 : x0 + bw] = d
    right = cv2.remap(tex, xx + disp_right, yy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    left = tex
    # left ground truth: every right pixel lands at x + d in the left image; nearest wins
    xl = np.rint(xx + disp_right).astype(np.int64)
    ok = xl < w
    flat = (yy.astype(np.int64) * w + xl)[ok]
    gt = np.full(h * w, -np.inf, np.float32)
    np.maximum.at(gt, flat, disp_right[ok])
    gt = gt.reshape(h, w)
    mask = np.isfinite(gt)
    gt[~mask] = 0
    u8 = lambda a: np.clip(np.rint(a), 0, 255).astype(np.uint8)  # noqa: E731
    return u8(left), u8(right), gt, mask, searched


def accuracy(disp: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
    err = np.abs(disp - gt)[mask]
    valid = np.isfinite(err)
    err_all = np.where(valid, err, np.inf)
    return {
        "bad1_percent": round(100.0 * float((err_all > 1).mean()), 2),
        "bad2_percent": round(100.0 * float((err_all > 2).mean()), 2),
        "mae_px": round(float(err[valid].mean()), 3),
        "density_percent": round(100.0 * float(valid.mean()), 1),
    }


#: OpenCV StereoSGBM modes of the peers.
SGBM_MODES = {"raw-sgbm": cv2.STEREO_SGBM_MODE_SGBM, "raw-sgbm-hh": cv2.STEREO_SGBM_MODE_HH,
              "raw-sgbm-3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY}


def raw_sgbm(left, right, dmin, dmax, mode=cv2.STEREO_SGBM_MODE_SGBM):
    """OpenCV StereoSGBM as usually configured (block 3, P1/P2 = 8/32 * block^2, uniqueness 10)."""
    block = 3
    sgbm = cv2.StereoSGBM_create(
        minDisparity=dmin, numDisparities=16 * -(-(dmax - dmin) // 16), blockSize=block,
        P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1, uniquenessRatio=10,
        speckleWindowSize=100, speckleRange=2, mode=mode,
    )
    raw = sgbm.compute(left, right)
    disp = raw.astype(np.float32) / 16.0
    disp[raw < dmin * 16] = np.nan
    return disp


def _cpu_seconds() -> float:
    """CPU time of this process so far (user + system, all threads): less sensitive than
    the wall time to other jobs sharing the cores."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_case(case: str, engine: str, overrides: dict, data: Path = CONES) -> dict:
    sys.path.insert(0, str(ROOT))
    from recon3d.stereo.match import MatchParams, match

    left, right, gt, mask, (dmin, dmax) = load_cones(data) if case == "cones" else synthetic_pair(case)
    h, w = left.shape
    cpu = _cpu_seconds()
    t = time.perf_counter()
    if engine in SGBM_MODES:
        disp = raw_sgbm(left, right, dmin, dmax, SGBM_MODES[engine])
        seconds, info = time.perf_counter() - t, {}
    else:
        params = MatchParams(min_disparity=dmin, max_disparity=dmax, engine=engine, **overrides)
        result = match(left, right, params)
        seconds = time.perf_counter() - t
        disp, info = result.disparity, result.params
    ndisp = dmax - dmin
    out = {
        "case": case,
        "engine": engine,
        "overrides": overrides,
        "size": f"{w}x{h}",
        "disparities": ndisp,
        "seconds": round(seconds, 2),
        "cpu_seconds": round(_cpu_seconds() - cpu, 2),
        "mpix_disp_per_s": round(w * h * ndisp / 1e6 / seconds, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 0),
        **accuracy(disp, gt, mask),
    }
    if info:
        out["searched"] = info["disparity_range_searched"]["value"]
        out["stage_seconds"] = info["seconds"]
        if "strip_disparity_ranges" in info:
            out["strip_ranges"] = info["strip_disparity_ranges"]
    if case == "cones" and engine not in SGBM_MODES:
        out["unfilled"] = accuracy(result.unfilled, gt, mask)
    return out


#: The figures printed beside raw OpenCV SGBM's, with their ratio.
RATIO_KEYS = [("bad1_percent", "bad-1 %"), ("bad2_percent", "bad-2 %"), ("mae_px", "mean abs error px"),
              ("density_percent", "density %"), ("seconds", "seconds"), ("cpu_seconds", "CPU seconds"), ("peak_rss_mb", "peak RSS MB")]


def print_ratios(rows: list[dict]) -> None:
    """Each recon3d engine beside each raw OpenCV SGBM mode on the same case."""
    for r in rows:
        if r["engine"] in SGBM_MODES:
            continue
        for peer in rows:
            if peer["case"] == r["case"] and peer["engine"] in SGBM_MODES:
                label = {"raw-sgbm": "SGBM", "raw-sgbm-hh": "SGBM HH", "raw-sgbm-3way": "SGBM 3WAY"}[peer["engine"]]
                _bench.print_ratios(f"{r['case']}, recon3d {r['engine']}", label, r, peer, RATIO_KEYS)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--case", choices=("cones", *SYNTHETIC))
    parser.add_argument("--engine", choices=("census", "sgbm", *SGBM_MODES))
    parser.add_argument(
        "--set", default="{}", help='MatchParams overrides as JSON, e.g. \'{"paths": 4}\''
    )
    parser.add_argument("--data", type=Path, default=CONES, help="the Middlebury cones folder (default: %(default)s)")
    _bench.add_quick(parser)
    args = parser.parse_args()
    if args.quick:
        args.case = "cones"
    if args.case in (None, "cones"):
        for name in CONES_FILES:
            _bench.require(args.data / name, "Middlebury cones file")
    if args.case and args.engine:
        print(json.dumps(run_case(args.case, args.engine, json.loads(args.set), args.data)))
        return 0
    cases = [(c, e) for c in ("cones", *SYNTHETIC) for e in (*SGBM_MODES, "sgbm", "census")
             if (args.case in (None, c)) and (args.engine in (None, e))]
    print(
        f"{'case':10s} {'engine':13s} {'size':>10s} {'D':>4s} {'s':>6s} {'CPU s':>6s} {'Mpx*D/s':>8s}"
        f" {'RSS MB':>7s} {'bad1%':>6s} {'bad2%':>6s} {'MAE':>6s} {'dens%':>6s}"
    )
    rows, failed = [], 0
    for case, engine in cases:
        proc = subprocess.run(
            [sys.executable, __file__, "--case", case, "--engine", engine, "--set", args.set, "--data", str(args.data)],
            capture_output=True, text=True, check=False,
        )
        if proc.returncode:
            print(f"{case} {engine}: failed\n{proc.stderr[-2000:]}")
            failed += 1
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(r)
        print(
            f"{r['case']:10s} {r['engine']:13s} {r['size']:>10s} {r['disparities']:4d}"
            f" {r['seconds']:6.2f} {r['cpu_seconds']:6.2f} {r['mpix_disp_per_s']:8.1f} {r['peak_rss_mb']:7.0f}"
            f" {r['bad1_percent']:6.2f} {r['bad2_percent']:6.2f} {r['mae_px']:6.3f}"
            f" {r['density_percent']:6.1f}"
        )
        if "unfilled" in r:
            u = r["unfilled"]
            print(
                f"{'':10s} {'unfilled':13s} {'':>10s} {'':>4s} {'':>6s} {'':>6s} {'':>8s} {'':>7s}"
                f" {u['bad1_percent']:6.2f} {u['bad2_percent']:6.2f} {u['mae_px']:6.3f}"
                f" {u['density_percent']:6.1f}"
            )
        if "stage_seconds" in r:
            print(f"{'':10s} stages: {r['stage_seconds']}, searched {r['searched']}"
                  + (f", per strip {r['strip_ranges']}" if "strip_ranges" in r else ""))
    print_ratios(rows)
    return 1 if failed else 0


if __name__ == "__main__":
    _bench.guard(main)
