"""Benchmark: frame stereo on the synthetic survey family, side by side with plain OpenCV.

For every survey of :mod:`recon3d.synthetic.family` (the named corner cases, then random
ones), renders the scene, runs ``recon3d run`` on it and, on the same images and
cameras, the plain OpenCV pipeline a user would otherwise write
(``cv2.stereoRectify`` + ``cv2.StereoSGBM`` + highest point per cell, images turned 90
degrees when the base runs along the columns), and scores both against the truth
(:mod:`recon3d.synthetic.score`). Prints one table; ``--json`` keeps every figure.
Columns: ``match%`` the truth's common area recon3d matched (not filled in), ``vis%``
the share of it both images see unhidden (an upper bound on ``match%``), ``m/vis%``
recon3d's own estimate of matched of visible (run.json ``stereo.common_area``),
``RMSboth`` the tolerant DSM RMS over the cells both recon3d and OpenCV fill (the same
ground for both, since OpenCV leaves much of a wide-base survey empty).

    .venv/bin/python scripts/bench_frame_stereo.py                 # full size, 9 named + 4 random
    .venv/bin/python scripts/bench_frame_stereo.py --width 800 --random 10
    .venv/bin/python scripts/bench_frame_stereo.py --only nadir_pair --vectors
    .venv/bin/python scripts/bench_frame_stereo.py --only random_45 random_52 --width 1000
    .venv/bin/python scripts/bench_frame_stereo.py --surveys development --width 1000
    .venv/bin/python scripts/bench_frame_stereo.py --surveys held-out --width 1000

``--surveys development``: the 25 surveys (9 named, 16 random) the matcher's rules were
measured and chosen on; ``--surveys held-out``: random surveys no rule was ever tuned
on, to tell a gain that generalises from one fitted to the development set. Keep
adding seeds to the held-out set, never move one the other way.

``--vectors`` also runs recon3d with the truth footprints (eave and ridge heights), the
spot heights and the coarse DEM of ``truth/`` as matching constraints (vector-constrained
matching), to measure their gain; the footprints then also give the building outlines.
``--scenes DIR`` keeps the rendered scenes (about half of a run's time with 3 x 3 rays)
for the next run, until the code that renders them changes.
``--quick``: ``nadir_pair`` alone at 320 px wide. ``--pixel-samples 3`` renders each pixel
from 3 x 3 rays over its area (see :class:`recon3d.synthetic.render.Lighting`): one ray
per pixel, the default, aliases the scene's finest texture on surfaces one view
foreshortens, which no real camera does.

When bulldozer-dtm (CNES, ``pip install -e ".[bench]"``) is installed, it also turns
recon3d's own DSM into a DTM, the DSM-to-DTM peer a user of a stereo DSM would run: its
ground check points are printed beside recon3d's DTM (column ``gndDTM``).
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import resource
import shutil
import tempfile
import time
from pathlib import Path

import _bench
import cv2
import numpy as np

from recon3d.config import PipelineConfig
from recon3d.core.raster import Raster, grid_for_bounds
from recon3d.io.colmap import read_scene
from recon3d.io.geotiff import read_raster
from recon3d.pipeline.run import run
from recon3d.synthetic.family import CONFIGURATIONS, family, random_spec
from recon3d.synthetic.render import Lighting
from recon3d.synthetic.scene import scene_city, write_block_scene
from recon3d.synthetic.score import _on_grid, _rms, score_stereo, tolerant_error
from recon3d.terrain.dsm import grid_points


def opencv_baseline(folder: Path, cell: float) -> tuple[Raster, float]:
    """Plain OpenCV on the scene's pairs: rectify, SGBM, reproject, highest point per cell."""
    scene = read_scene(folder)
    t0 = time.perf_counter()
    points = []
    for i in range(len(scene.cameras)):
        for j in range(i + 1, len(scene.cameras)):
            common = scene.seen[i] & scene.seen[j]
            if common.sum() >= 10:
                points.append(_baseline_pair(scene.cameras[i], scene.cameras[j], scene.sparse[common]))
    # keep what lies near the sparse points (a user crops to the area of interest)
    lo, hi = scene.sparse.min(axis=0), scene.sparse.max(axis=0)
    pad = 0.2 * (hi - lo) + np.array([0.0, 0.0, 30.0])
    xyz = np.concatenate(points)
    xyz = xyz[np.isfinite(xyz).all(axis=1) & (xyz >= lo - pad).all(axis=1) & (xyz <= hi + pad).all(axis=1)]
    if not len(xyz):
        raise ValueError("OpenCV's pairs gave no point near the sparse points")
    xyz = xyz + scene.offset
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], cell)
    dsm = grid_points(xyz, transform, shape, reducer="max")
    return Raster(dsm.astype(np.float32), transform, scene.crs), time.perf_counter() - t0


def _baseline_pair(a, b, sparse: np.ndarray) -> np.ndarray:
    img_a, img_b = cv2.imread(str(a.image_path)), cv2.imread(str(b.image_path))
    R = b.R @ a.R.T
    T = b.t - R @ a.t
    turn = abs(T[1]) > abs(T[0])
    if turn:  # OpenCV rectifies a column base vertically; SGBM matches rows: turn both views
        rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        a, b = (_turned(c, rot) for c in (a, b))
        img_a, img_b = (cv2.rotate(i, cv2.ROTATE_90_CLOCKWISE) for i in (img_a, img_b))
        R, T = rot @ R @ rot.T, rot @ T
    if T[0] > 0:  # b on the left: swap for positive disparities
        a, b, img_a, img_b = b, a, img_b, img_a
        R, T = R.T, -R.T @ T
    size = (a.width, a.height)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(a.K, a.dist, b.K, b.dist, size, R, T.reshape(3, 1))
    maps = [cv2.initUndistortRectifyMap(c.K, c.dist, Rr, P, size, cv2.CV_32FC1)
            for c, Rr, P in ((a, R1, P1), (b, R2, P2))]
    left = cv2.remap(cv2.cvtColor(img_a, cv2.COLOR_BGR2GRAY), *maps[0], cv2.INTER_LINEAR)
    right = cv2.remap(cv2.cvtColor(img_b, cv2.COLOR_BGR2GRAY), *maps[1], cv2.INTER_LINEAR)
    cam = sparse @ a.R.T + a.t
    rect = cam @ R1.T
    d = (rect[:, 0] * P1[0, 0] / rect[:, 2] + P1[0, 2]) - ((rect[:, 0] * P2[0, 0] + P2[0, 3]) / rect[:, 2] + P2[0, 2])
    dmin = int(np.floor(d.min())) - 8
    ndisp = 16 * int(np.ceil((d.max() + 8 - dmin) / 16))
    block = 5
    sgbm = cv2.StereoSGBM_create(minDisparity=dmin, numDisparities=ndisp, blockSize=block,
                                 P1=8 * block * block, P2=32 * block * block, uniquenessRatio=10,
                                 speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1)
    disp = sgbm.compute(left, right).astype(np.float32) / 16.0
    ok = (disp > dmin) & (disp > 0)  # disparity 0 is a point at infinity
    xyz_rect = cv2.reprojectImageTo3D(disp, Q)[ok].astype(np.float64)
    xyz_cam = xyz_rect @ R1  # rectified to camera frame
    return (xyz_cam - a.t) @ a.R


def _turned(cam, rot):
    from recon3d.core.camera import Camera

    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    K = np.array([[fy, 0.0, cam.height - 1 - cy], [0.0, fx, cx], [0.0, 0.0, 1.0]])
    k1, k2, p1, p2, k3 = cam.dist
    return Camera(cam.name, K, np.array([k1, k2, p2, -p1, k3]), rot @ cam.R, rot @ cam.t,
                  cam.height, cam.width, cam.image_path)


def render(spec, pixel_samples: int, tmp: Path, scenes: Path | None = None) -> tuple[Path, float]:
    """The scene folder of ``spec`` and the seconds its rendering took. Rendered into
    ``tmp``; with ``scenes``, kept there under a key of the spec, the rays per pixel and
    the source of the code that renders it, and found there again (0 s) by the next run
    while that code is unchanged."""
    lighting = Lighting(pixel_samples=pixel_samples)
    if scenes is None:
        t = time.perf_counter()
        write_block_scene(tmp / spec.name, spec, lighting=lighting)
        return tmp / spec.name, time.perf_counter() - t
    folder = scenes / f"{spec.name}-{scene_key(spec, pixel_samples)}"
    if (folder / "truth" / "scene.json").exists():
        return folder, 0.0
    scenes.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=scenes))
    t = time.perf_counter()
    write_block_scene(scratch, spec, lighting=lighting)
    seconds = time.perf_counter() - t
    try:
        scratch.rename(folder)  # whole or not at all: a run killed while rendering leaves only the scratch
    except OSError:  # another run kept the same scene meanwhile
        shutil.rmtree(scratch)
    return folder, seconds


def scene_key(spec, pixel_samples: int) -> str:
    """16 hex digits of the SHA-256 of the spec, the rays per pixel and the source of
    the packages the rendered scene depends on (:func:`_rendering_source`)."""
    digest = hashlib.sha256(json.dumps([spec.to_dict(), pixel_samples], sort_keys=True).encode())
    digest.update(_rendering_source())
    return digest.hexdigest()[:16]


@functools.cache
def _rendering_source() -> bytes:
    """SHA-256 of the source of the synthetic city and renderer, the cameras and the
    writers: read once per run, not once per scene."""
    import recon3d

    digest = hashlib.sha256()
    package = Path(recon3d.__file__).parent
    for sub in ("synthetic", "core", "io"):
        for path in sorted((package / sub).glob("*.py")):
            digest.update(path.read_bytes())
    return digest.digest()


def bench_one(spec, tmp: Path, *, vectors: bool, overrides: list[str] | None = None, pixel_samples: int = 1,
              scenes: Path | None = None) -> dict:
    folder, render_s = render(spec, pixel_samples, tmp, scenes)
    city = scene_city(folder)
    truth = folder / "truth"
    row = {"scene": spec.name, "images": spec.strips * spec.images_per_strip, "size": f"{spec.width}x{spec.height}",
           "render_s": round(render_s, 1), "spec": spec.to_dict(), "pixel_samples": pixel_samples}
    runs = {"recon3d": {}}
    if vectors:
        runs["recon3d+vectors"] = {"footprints": truth / "footprints.geojson", "altimetry": truth / "spot_heights.csv",
                                   "dem": truth / "coarse_dem.tif"}
    for name, extra in runs.items():
        t = time.perf_counter()
        try:
            config = PipelineConfig().with_overrides(overrides) if overrides else None
            state = run(folder, tmp / f"out-{spec.name}-{name}", checkpoints=truth / "checkpoints.csv", overwrite=True,
                        config=config, **extra)
        except Exception as exc:  # a failure is a result too
            row[name] = {"error": str(exc)[:300]}
            continue
        observed = ~state.dsm_filled & np.isfinite(state.dsm.data)
        if state.dsm_unobserved is not None:
            observed &= ~state.dsm_unobserved
        score = score_stereo(folder, state.dsm, dtm=state.dtm, footprints=[b.footprint for b in state.city],
                             observed=observed, city=city)
        score["seconds"] = round(time.perf_counter() - t, 2)
        score["stereo_seconds"] = state.timings.get("stereo")
        score["warnings"] = state.warnings
        score["matched_of_visible"] = state.auto["stereo"]["common_area"].get("matched_of_visible_percent")
        score["pairs"] = [{k: p.get(k) for k in ("pair", "matched_percent", "self_check")} for p in state.auto["stereo"]["pairs"]]
        row[name] = score
        cell = state.dsm.resolution
        if name == "recon3d":
            peer = bulldozer_dtm(state.out_dir / "dsm.tif", tmp / f"bulldozer-{spec.name}", truth)
            if peer is not None:
                row["bulldozer"] = peer
    try:
        dsm, seconds = opencv_baseline(folder, cell if "recon3d" in row and "error" not in row["recon3d"] else 0.5)
    except (cv2.error, ValueError) as exc:  # e.g. SGBM refuses a disparity range wider than the rectified image
        row["opencv"] = {"error": " ".join(str(exc).split())[:300]}
        return row
    score = score_stereo(folder, dsm, city=city)
    score["ground_rms_dsm"] = _ground_on(dsm, truth)
    score["seconds"] = round(seconds, 2)
    row["opencv"] = score
    if "recon3d" in row and "error" not in row["recon3d"]:
        row["recon3d"]["rms_shared"] = _rms_where_both(folder, state.dsm, dsm, city)
        score["rms_shared"] = _rms_where_both(folder, dsm, state.dsm, city)
    return row


def _rms_where_both(folder: Path, dsm: Raster, other: Raster, city) -> float | None:
    """Tolerant DSM RMS of ``dsm`` over the common cells ``other`` also fills: the two
    pipelines' accuracy on the same ground, whatever each left empty."""
    common = _on_grid(read_raster(folder / "truth" / "views.tif"), dsm) >= 2
    return _rms(tolerant_error(city, dsm, common & np.isfinite(_on_grid(other, dsm))))


def bulldozer_dtm(dsm_path: Path, out: Path, truth: Path) -> dict | None:
    """bulldozer-dtm's DTM of ``dsm_path`` (its defaults, 2 workers) scored on the ground
    check points; None when bulldozer is not installed."""
    import contextlib
    import io

    try:
        from bulldozer.pipeline.bulldozer_pipeline import dsm_to_dtm
    except ImportError:
        return None
    t = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):  # its progress bars
        dsm_to_dtm(dsm_path=str(dsm_path), output_dir=str(out), nb_max_workers=2)
    seconds = round(time.perf_counter() - t, 2)
    return {"ground_rms": _ground_on(read_raster(out / "dtm.tif"), truth), "seconds": seconds}


def _ground_on(dsm: Raster, truth: Path) -> float | None:
    from recon3d.synthetic.score import _checkpoints

    views = read_raster(truth / "views.tif")
    xyz, kinds = _checkpoints(truth / "checkpoints.csv")
    inside = np.nan_to_num(views.sample(xyz[:, 0], xyz[:, 1], bilinear=False)) >= 2
    sel = inside & (kinds == "ground")
    e = dsm.sample(xyz[sel, 0], xyz[sel, 1]) - xyz[sel, 2]
    e = e[np.isfinite(e)]
    return round(float(np.sqrt(np.mean(e**2))), 3) if e.size else None


COLUMNS = [
    ("coverage", "cover%"), ("observed", "match%"), ("visible", "vis%"), ("matched_of_visible", "m/vis%"),
    ("dsm_rms_tolerant", "RMStol"), ("rms_shared", "RMSboth"), ("dsm_within_1m", "<=1m%"),
    ("ground_rms", "gndDTM"), ("roof_rms", "roof"), ("footprint_completeness", "compl%"),
    ("footprint_correctness", "corr%"), ("object_completeness", "oComp%"), ("object_correctness", "oCorr%"),
    ("seconds", "s"),
]


def print_table(rows: list[dict]) -> None:
    names = [n for n in ("recon3d", "recon3d+vectors", "opencv", "bulldozer") if any(n in r for r in rows)]
    head = f"{'scene':<15}{'who':<16}" + "".join(f"{c:>8}" for _, c in COLUMNS)
    print(head)
    for r in rows:
        for n in names:
            res = r.get(n)
            if res is None:
                continue
            if "error" in res:
                print(f"{r['scene']:<15}{n:<16}error: {res['error'][:100]}")
                continue
            cells = []
            for key, _ in COLUMNS:
                v = res.get("ground_rms_dsm") if (key == "ground_rms" and n == "opencv") else res.get(key)
                cells.append(f"{v:>8.2f}" if isinstance(v, float | int) else f"{'-':>8}")
            print(f"{r['scene']:<15}{n:<16}" + "".join(cells))


#: The figures printed beside OpenCV's, with their ratio.
RATIO_KEYS = [("coverage", "coverage %"), ("dsm_rms_tolerant", "DSM RMS (tolerant) m"),
              ("rms_shared", "DSM RMS where both fill m"),
              ("dsm_within_1m", "DSM within 1 m %"), ("roof_rms", "roof RMS m"), ("seconds", "s (recon3d: whole run)")]

#: ``--quick``: the survey and the image width.
QUICK = ("nadir_pair", 320)
#: Random seeds of ``--surveys development``, after the named configurations.
DEVELOPMENT_SEEDS = (1, 4, 6, 17, 40, 41, 42, 44, 45, 46, 47, 51, 52, 53, 55, 56)
#: Random seeds of ``--surveys held-out``: never looked at while designing.
HELD_OUT_SEEDS = (61, 62, 63, 64)


def print_ratios(rows: list[dict]) -> None:
    """recon3d beside plain OpenCV, scene by scene, with recon3d / OpenCV."""
    for r in rows:
        ours, theirs = r.get("recon3d", {}), r.get("opencv", {})
        if "error" not in ours and "error" not in theirs:
            _bench.print_ratios(r["scene"], "OpenCV", ours, theirs, RATIO_KEYS)
        if "error" not in ours and "bulldozer" in r:
            _bench.print_ratios(r["scene"], "bulldozer", ours, r["bulldozer"], [("ground_rms", "ground check pts m")])


def print_summary(rows: list[dict]) -> None:
    """Median over the surveys of every column, per pipeline."""
    for n in ("recon3d", "recon3d+vectors", "opencv", "bulldozer"):
        ok = [r[n] for r in rows if n in r and "error" not in r[n]]
        if not ok:
            continue
        cells = []
        for key, _ in COLUMNS:
            key = "ground_rms_dsm" if (key == "ground_rms" and n == "opencv") else key
            vals = [v[key] for v in ok if isinstance(v.get(key), float | int)]
            cells.append(f"{np.median(vals):>8.2f}" if vals else f"{'-':>8}")
        print(f"{'median':<15}{n:<16}" + "".join(cells))


def survey(name: str):
    """The survey called ``name``: a named configuration, or ``random_N`` (seed N); None if neither."""
    if name in CONFIGURATIONS:
        return CONFIGURATIONS[name]
    prefix, _, seed = name.partition("_")
    return random_spec(int(seed)) if prefix == "random" and seed.isdigit() else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, help="image width (px) for every survey, same geometry (default: full size)")
    parser.add_argument("--random", type=int, default=4, help="random surveys after the named ones")
    parser.add_argument("--only", nargs="*", metavar="SURVEY",
                        help="surveys to run: named configurations, or random_N for the random survey of seed N")
    parser.add_argument("--surveys", choices=("development", "held-out"),
                        help="a fixed set instead of the named ones and --random: the 25 the rules were "
                             "chosen on, or the random ones held out from that")
    parser.add_argument("--vectors", action="store_true", help="also run with the truth footprints as constraints")
    parser.add_argument("--json", type=Path, help="write every figure here")
    parser.add_argument("--set", dest="overrides", action="append", metavar="STAGE.KEY=VALUE",
                        help="a recon3d setting for every run, as on the command line (repeatable)")
    parser.add_argument("--pixel-samples", type=int, default=1, metavar="K",
                        help="render each pixel from K x K rays over its area, as a sensor integrates the light "
                             "(default 1: one ray per pixel centre, whose fine texture aliases on foreshortened "
                             "surfaces); 3 is close to a real camera")
    parser.add_argument("--scenes", type=Path, metavar="DIR",
                        help="keep the rendered scenes in DIR and reuse them on the next run (each under a key of "
                             "its spec, its rays per pixel and the rendering code's source)")
    _bench.add_quick(parser)
    args = parser.parse_args()
    if args.quick:
        args.only, args.width = [QUICK[0]], QUICK[1]
    if args.pixel_samples < 1:
        _bench.refuse(f"--pixel-samples {args.pixel_samples}: at least 1")
    unknown = sorted(n for n in args.only or () if survey(n) is None)
    if unknown:
        _bench.refuse(f"no survey named {', '.join(unknown)}; known: {', '.join(sorted(CONFIGURATIONS))}, "
                      "random_N (N >= 0)")
    if args.only:
        specs = [survey(n) for n in args.only]
    elif args.surveys == "development":
        specs = [*CONFIGURATIONS.values(), *(random_spec(k) for k in DEVELOPMENT_SEEDS)]
    elif args.surveys == "held-out":
        specs = [random_spec(k) for k in HELD_OUT_SEEDS]
    else:
        specs = family(args.random)
    if args.width:
        specs = [s.with_width(args.width) for s in specs]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for spec in specs:
            rows.append(bench_one(spec, Path(tmp), vectors=args.vectors, overrides=args.overrides,
                                  pixel_samples=args.pixel_samples, scenes=args.scenes))
            print_table(rows[-1:])
    print()
    print_table(rows)
    print_summary(rows)
    print_ratios(rows)
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=str))


if __name__ == "__main__":
    _bench.guard(main)
