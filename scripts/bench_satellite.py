"""Benchmark: satellite (RPC) stereo on synthetic pairs with exact truth, side by side with peers.

For every pair of :data:`recon3d.synthetic.satellite.SATELLITE_SCENES` (steep mountains
with a village, a town on hills, a flat desert), renders the two pushbroom images, fits
their RPCs, runs ``recon3d run img1.tif img2.tif`` and scores the DSM, DTM and
footprints against the truth (:mod:`recon3d.synthetic.score`), beside:

- recon3d with the OpenCV SGBM engine (``stereo.engine = "sgbm"``) on its own
  rectification, the matcher s2p also uses;
- CARS (CNES), when ``--cars PATH`` names its ``cars`` executable (it lives in its own
  virtual environment: ``python -m venv v && v/bin/pip install cars``), through
  ``scripts/peer_cars.py``;
- s2p, when ``--s2p PATH`` names its ``s2p`` executable (its own virtual environment, see
  ``scripts/peer_s2p.py`` for the build), through ``scripts/peer_s2p.py``.

Peers' DSMs are scored on their own grids (CARS 0.5-0.7 m, s2p 0.5 m, recon3d 1 m by
default) against the same truth; they make no DTM and no buildings.

``--giza`` also runs the shared Pleiades pair and prints the checks of issue 16 there.
Each peer that ran is printed beside recon3d with the ratio. A peer named by ``--cars``
or ``--s2p`` that is not there stops a full run; ``--quick`` (the mountain scene, 80 m,
recon3d alone beside the peers given) skips it with a note.

    .venv/bin/python scripts/bench_satellite.py                      # 400 m scenes (880 px)
    .venv/bin/python scripts/bench_satellite.py --size 500 --only mountain
    .venv/bin/python scripts/bench_satellite.py --cars /work/peers/.venv-cars/bin/cars \
        --s2p /work/peers/.venv-s2p/bin/s2p --giza
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _bench
import numpy as np

from recon3d.config import PipelineConfig
from recon3d.io.geotiff import read_raster
from recon3d.pipeline.run import run
from recon3d.synthetic.satellite import SATELLITE_SCENES, write_satellite_scene
from recon3d.synthetic.scene import scene_city
from recon3d.synthetic.score import score_stereo

HERE = Path(__file__).resolve().parent
GIZA = _bench.SHARED / "stereo" / "pleiades_gizeh"
QUICK = ("mountain", 80.0)  # --quick: scene and side (m)
PEER_INSTALL = {"cars": "its own venv: python -m venv v && v/bin/pip install cars",
                "s2p": "its own venv, built as scripts/peer_s2p.py describes"}
KHUFU = (31.134225, 29.979175)  # lon, lat of the Great Pyramid's apex


def run_recon3d(folder: Path, out: Path, config: PipelineConfig | None, city):
    t = time.perf_counter()
    truth = folder / "truth"
    state = run((folder / "img1.tif", folder / "img2.tif"), out, checkpoints=truth / "checkpoints.csv",
                overwrite=True, config=config)
    observed = np.isfinite(state.dsm.data) & ~state.dsm_filled
    if state.dsm_unobserved is not None:
        observed &= ~state.dsm_unobserved
    score = score_stereo(folder, state.dsm, dtm=state.dtm, footprints=[b.footprint for b in state.city],
                         observed=observed, city=city)
    stereo = state.auto["stereo"]
    score.update(seconds=round(time.perf_counter() - t, 1), stereo_seconds=state.timings.get("stereo"),
                 matched_percent=stereo.get("matched_percent"), buildings=len(state.city),
                 truth_buildings=len(city.buildings), warnings=state.warnings)
    return score, state.dsm


def run_peer(script: str, folder: Path, out: Path, option: str, executable: str, city):
    """A peer pipeline through its runner script (``peer_cars.py``, ``peer_s2p.py``), scored like recon3d."""
    t = time.perf_counter()
    done = subprocess.run([sys.executable, str(HERE / script), str(folder / "img1.tif"), str(folder / "img2.tif"),
                           "-o", str(out), option, executable], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError((done.stderr or done.stdout)[-300:])
    dsm_path = Path(next(line for line in done.stdout.splitlines() if line.startswith("DSM: "))[5:].strip())
    dsm = read_raster(dsm_path)
    score = score_stereo(folder, dsm, city=city)
    score["seconds"] = round(time.perf_counter() - t, 1)
    return score, dsm


def on_common_cells(folder: Path, dsms: dict) -> dict:
    """Each DSM's error on the truth grid, over the cells both images see and every DSM fills.

    Pipelines that leave occlusions empty (s2p) score their own, easier cells in the
    main table; here every pipeline is measured on the same cells.
    """
    from recon3d.synthetic.score import _on_grid

    truth = read_raster(folder / "truth" / "dsm.tif")
    views = _on_grid(read_raster(folder / "truth" / "views.tif"), truth)
    on = {who: _on_grid(dsm, truth) for who, dsm in dsms.items()}
    cells = (views >= 2) & np.isfinite(truth.data) & np.all([np.isfinite(v) for v in on.values()], axis=0)
    out = {}
    for who, z in on.items():
        e = (z - truth.data)[cells]
        med = float(np.median(e))
        out[who] = {"share_of_common_percent": round(100.0 * float(cells.sum() / max((views >= 2).sum(), 1)), 1),
                    "median": round(med, 3), "nmad": round(float(1.4826 * np.median(np.abs(e - med))), 3),
                    "within_1m": round(100.0 * float(np.mean(np.abs(e) <= 1.0)), 2),
                    "rms": round(float(np.sqrt(np.mean(e**2))), 3)}
    return out


COLUMNS = [
    ("coverage", "cover%"), ("observed", "obs%"), ("matched_percent", "match%"), ("dsm_nmad", "NMAD"),
    ("dsm_median", "median"), ("dsm_rms_tolerant", "RMStol"), ("dsm_within_1m", "<=1m%"), ("ground_rms", "gndDTM"),
    ("roof_rms", "roof"), ("footprint_completeness", "compl%"), ("footprint_correctness", "corr%"),
    ("buildings", "bldgs"), ("stereo_seconds", "stereo_s"), ("seconds", "s"),
]


def print_rows(rows: list[dict]) -> None:
    print(f"{'scene':<10}{'who':<14}" + "".join(f"{c:>9}" for _, c in COLUMNS))
    for r in rows:
        for who, res in r["runs"].items():
            if "error" in res:
                print(f"{r['scene']:<10}{who:<14}error: {res['error'][:120]}")
                continue
            cells = [f"{res[k]:>9.2f}" if isinstance(res.get(k), float | int) else f"{'-':>9}" for k, _ in COLUMNS]
            print(f"{r['scene']:<10}{who:<14}" + "".join(cells))


def bench_scene(name: str, size: float, tmp: Path, cars: str | None, s2p: str | None, sgbm_run: bool = True) -> dict:
    spec = dataclasses.replace(SATELLITE_SCENES[name], size=size)
    folder = tmp / name
    t = time.perf_counter()
    made = write_satellite_scene(folder, spec)
    row = {"scene": name, "pixels": made["cameras"][0].width, "render_s": round(time.perf_counter() - t, 1), "runs": {}}
    city = scene_city(folder)
    sgbm = PipelineConfig().with_overrides(["stereo.engine=sgbm"])
    runs = {"recon3d": lambda: run_recon3d(folder, tmp / f"out-{name}-recon3d", None, city)}
    if sgbm_run:
        runs["recon3d-sgbm"] = lambda: run_recon3d(folder, tmp / f"out-{name}-sgbm", sgbm, city)
    if cars:
        runs["cars"] = lambda: run_peer("peer_cars.py", folder, tmp / f"out-{name}-cars", "--cars", cars, city)
    if s2p:
        runs["s2p"] = lambda: run_peer("peer_s2p.py", folder, tmp / f"out-{name}-s2p", "--s2p", s2p, city)
    dsms = {}
    for who, job in runs.items():
        try:
            row["runs"][who], dsms[who] = job()
        except Exception as exc:  # a failure is a result too
            row["runs"][who] = {"error": str(exc)[-300:]}
    row["common_cells"] = on_common_cells(folder, dsms)
    return row


def print_common(rows: list[dict]) -> None:
    print(f"{'scene':<10}{'who':<14}{'cells%':>9}{'median':>9}{'NMAD':>9}{'<=1m%':>9}{'RMS':>9}   (same cells for all)")
    for r in rows:
        for who, c in r.get("common_cells", {}).items():
            print(f"{r['scene']:<10}{who:<14}{c['share_of_common_percent']:>9.1f}{c['median']:>9.3f}{c['nmad']:>9.3f}"
                  f"{c['within_1m']:>9.2f}{c['rms']:>9.3f}")


#: The figures printed beside a peer's, with their ratio (main table, then the common cells).
RATIO_KEYS = [("coverage", "coverage %"), ("dsm_nmad", "DSM NMAD m"), ("dsm_rms_tolerant", "DSM RMS (tolerant) m"),
              ("dsm_within_1m", "DSM within 1 m %"), ("seconds", "seconds")]
COMMON_KEYS = [("nmad", "common NMAD m"), ("rms", "common RMS m"), ("within_1m", "common within 1 m %")]


def print_ratios(rows: list[dict]) -> None:
    """recon3d beside each peer that ran (CARS, s2p), scene by scene."""
    for r in rows:
        ours = r["runs"].get("recon3d", {})
        for peer in ("cars", "s2p"):
            theirs = r["runs"].get(peer)
            if theirs is None or "error" in theirs or "error" in ours:
                continue
            common = r.get("common_cells", {})
            _bench.print_ratios(f"{r['scene']}", peer, ours, theirs, RATIO_KEYS)
            _bench.print_ratios(f"{r['scene']}, same cells", peer, common.get("recon3d", {}), common.get(peer, {}),
                                COMMON_KEYS)


def check_peers(args) -> None:
    """Peers named but not there: refused in a full run, dropped with a note in ``--quick``."""
    for peer in ("cars", "s2p"):
        given = getattr(args, peer)
        if given is None:
            if args.quick:
                print(f"note: {peer} not run (--{peer} PATH names its executable)")
            continue
        if shutil.which(given) is None:
            _bench.peer_missing(peer, f"--{peer} {given} is no executable; {PEER_INSTALL[peer]}", args.quick)
            setattr(args, peer, None)


def giza_checks(tmp: Path) -> dict:
    """The Giza checks of issue 16 on the shared Pleiades pair."""
    import pyproj

    from recon3d.quality.evaluate import landmark_height

    state = run((GIZA / "img1.tif", GIZA / "img2.tif"), tmp / "out-giza", overwrite=True)
    stereo = state.auto["stereo"]
    ties = stereo.get("tie_heights_m", [np.nan, np.nan])
    dsm, dtm = state.dsm.data, state.dtm.data
    return {
        "matched_percent": stereo.get("matched_percent"),
        "tie_heights_m": ties,
        "dsm_min": float(np.nanmin(dsm)), "dtm_min": float(np.nanmin(dtm)),
        "dsm_cells_below_ties_minus_10m": int(np.sum(dsm < ties[0] - 10.0)),
        "dtm_cells_below_ties_minus_10m": int(np.sum(dtm < ties[0] - 10.0)),
        "dsm_coverage": float(np.isfinite(dsm).mean()), "dtm_coverage": float(np.isfinite(dtm).mean()),
        "buildings": len(state.city),
        "khufu": landmark_height(state.dsm, *pyproj.Transformer.from_crs(4326, state.dsm.crs, always_xy=True)
                                 .transform(*KHUFU), search=60.0, ring=(118.0, 130.0)),
        "stereo_seconds": state.timings.get("stereo"),
        "warnings": state.warnings,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=float, default=400.0, help="side of each scene (m); 0.5 m GSD")
    parser.add_argument("--only", nargs="*", choices=sorted(SATELLITE_SCENES), help="scenes to run")
    parser.add_argument("--cars", help="the cars executable, to run CARS on the same pairs")
    parser.add_argument("--s2p", help="the s2p executable, to run s2p on the same pairs")
    parser.add_argument("--giza", action="store_true", help="also the checks on the shared Giza pair")
    parser.add_argument("--json", type=Path, help="write every figure here")
    _bench.add_quick(parser)
    args = parser.parse_args()
    if args.quick:
        args.only, args.size = [QUICK[0]], QUICK[1]
    if args.giza:
        for name in ("img1.tif", "img2.tif"):
            _bench.require(GIZA / name, "Pleiades image")
    check_peers(args)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.only or list(SATELLITE_SCENES):
            rows.append(bench_scene(name, args.size, Path(tmp), args.cars, args.s2p, sgbm_run=not args.quick))
            print_rows(rows[-1:])
        print()
        print_rows(rows)
        print()
        print_common(rows)
        print_ratios(rows)
        result = {"scenes": rows}
        if args.giza:
            result["giza"] = giza_checks(Path(tmp))
            print(json.dumps(result["giza"], indent=1, default=str))
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))


if __name__ == "__main__":
    _bench.guard(main)
