"""Benchmark: recon3d's ground filter against PDAL's SMRF and CSF (cloth simulation filter).

For every ``*.las`` / ``*.laz`` file in ``../shared/data/lidar`` (relative to the
repository root) four filters are scored against the provider's classes:

``recon3d``
    :func:`recon3d.terrain.ground.classify_ground` with ``GroundConfig()`` (automatic
    defaults) and the automatic DSM cell as ``cell``, as the pipeline calls it.
``pdal_smrf``
    PDAL's ``filters.smrf`` with its defaults, after ``filters.assign`` clears the
    provider's classes; its time is the whole ``pdal pipeline`` process (read, filter,
    write). PDAL is a peer only: conda-forge, Ubuntu's package, or on Debian
    ``sudo sh scripts/pdal_chroot.sh``; without it a full run refuses unless ``--no-pdal`` is given.
``csf``
    CSF (Zhang et al., 2016; the ``cloth-simulation-filter`` package) with the defaults
    of its constructor, read from ``CSF.CSF().params`` at run time.
``csf_oracle``
    The CSF run with the lowest total error over cloth_resolution {0.5, 1, 2} m x
    rigidness {1, 2, 3} x bSloopSmooth {False, True}. Chosen with the reference
    classes, so it is an optimistic bound on what CSF can do, not a fair competitor.

Scores: ISPRS Type I / Type II / total error and Cohen's kappa
(:func:`recon3d.quality.evaluate.ground_filter_errors`: provider class 2 against
3-6, other classes left out), and DTM RMS: the DTM from the method's ground
points minus the DTM from the provider's ground points (class 2), both made by
:func:`recon3d.terrain.dtm.make_dtm` on the automatic DSM grid, RMS in metres over
the cells within 2 cells (Euclidean) of a cell holding at least one provider
ground point, so large interpolated areas outside the reference (water, edges)
do not count. Speed is points per second of the filter call alone (best of
``--repeat`` runs; for CSF: ``setPointCloud`` + ``do_filtering``).

CSF is given coordinates shifted to the cloud's minimum corner and scaled to metres
(x, y by ``units.horizontal``, z by ``units.vertical``). This converts its metric
parameters (cloth resolution, class threshold) to the file's CRS units and also puts
CSF's hard-coded constants (gravity step, convergence and slope-smoothing thresholds,
all in data units) in metres; the shift keeps single-precision rounding away.

A file whose provider has no object class (3-6), like Autzen (classes 1 and 2 only),
scores Type I alone: its total error is Type I over the ground points, Type II is 0 and
kappa 0 by construction, so only its Type I and DTM RMS say anything.

Files without a CRS get the one in ``DEFAULT_CRS`` (Delft AHN3: EPSG:7415).
Needs the ``bench`` extra: ``pip install -e '.[bench]'``. ``--quick`` scores one file
(the IGN village, else the smallest), one timed run, no oracle grid, and without CSF
when it is not installed (a note says so).

    .venv/bin/python scripts/bench_ground.py [--json PATH] [--data DIR] [--repeat N] [--no-oracle] [--quick]
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import _bench
import numpy as np
from scipy import ndimage

from recon3d.config import DsmConfig, GroundConfig
from recon3d.core.geo import Units, crs_name, crs_units, parse_crs
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster
from recon3d.errors import CRSError, InputError
from recon3d.io.las import read_las
from recon3d.pipeline.run import HOLE_AREA
from recon3d.quality.evaluate import ground_filter_errors
from recon3d.terrain.dsm import choose_resolution, grid_points, make_dsm, point_spacing
from recon3d.terrain.dtm import make_dtm
from recon3d.terrain.ground import GroundResult, classify_ground

DATA = (Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lidar").resolve()

#: CRS for files whose header has none, by file name.
DEFAULT_CRS = {"delft_ahn3_strip.laz": "EPSG:7415"}

#: The oracle's grid: cloth resolution (m) x rigidness x slope smoothing.
ORACLE_GRID = {
    "cloth_resolution": (0.5, 1.0, 2.0),
    "rigidness": (1, 2, 3),
    "bSloopSmooth": (False, True),
}

#: Reference cells count when a provider ground point lies within this many cells.
MASK_CELLS = 2.0

#: The file ``--quick`` scores when the data folder has it (71k points, classes 2 and 6).
QUICK_FILE = "ign_village_2154.laz"

#: How to install the peers (benchmark-only, not dependencies).
CSF_INSTALL = "pip install -e '.[bench]'"

#: CSF's parameters (``interations`` is the package's spelling).
CSF_PARAMS = (
    "cloth_resolution", "rigidness", "bSloopSmooth", "time_step", "class_threshold", "interations"
)


# -- input --------------------------------------------------------------------------


def load(path: Path) -> tuple[PointCloud, Units]:
    try:
        cloud = read_las(path)
    except CRSError:
        if path.name not in DEFAULT_CRS:
            raise
        cloud = read_las(path, crs=parse_crs(DEFAULT_CRS[path.name]))
    return cloud, crs_units(cloud.crs, source=str(path))


# -- methods ------------------------------------------------------------------------


def run_recon3d(
    cloud: PointCloud, units: Units, cell: float, repeat: int
) -> tuple[GroundResult, float]:
    best, result = math.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        result = classify_ground(cloud, GroundConfig(), units, cell)
        best = min(best, time.perf_counter() - t)
    method = result.params.get("method")
    method = method.get("value") if isinstance(method, dict) else method
    if method == "provider":  # the benchmark would only compare the classes with themselves
        raise SystemExit("GroundConfig() picked method 'provider': nothing to benchmark")
    return result, best


def have_csf() -> bool:
    """True when the ``cloth-simulation-filter`` package (module ``CSF``) imports."""
    try:
        import CSF  # noqa: F401
    except ImportError:
        return False
    return True


def csf_defaults() -> dict:
    import CSF

    p = CSF.CSF().params
    return {name: getattr(p, name) for name in CSF_PARAMS}


@contextlib.contextmanager
def silenced_stdout():
    """Send file descriptor 1 to /dev/null: CSF's C++ code prints its progress there."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def run_csf(xyz_m: np.ndarray, params: dict, repeat: int = 1) -> tuple[np.ndarray, float]:
    """CSF on metric coordinates; returns (is_ground, best seconds)."""
    import CSF

    best, ground = math.inf, None
    for _ in range(repeat):
        csf = CSF.CSF()
        for name, value in params.items():
            setattr(csf.params, name, value)
        ground, off = CSF.VecInt(), CSF.VecInt()
        with silenced_stdout():
            t = time.perf_counter()
            csf.setPointCloud(xyz_m)
            csf.do_filtering(ground, off, exportCloth=False)
            best = min(best, time.perf_counter() - t)
    is_ground = np.zeros(len(xyz_m), bool)
    is_ground[np.asarray(ground, dtype=np.int64)] = True
    return is_ground, best


# -- scoring ------------------------------------------------------------------------


class Reference:
    """The provider's classes, DTM and the cells the DTM RMS is taken over."""

    def __init__(self, cloud: PointCloud, grid: Raster, units: Units):
        self.classes = cloud.classification
        self.xyz, self.grid, self.units = cloud.xyz, grid, units
        ground = self.xyz[self.classes == ASPRS.GROUND]
        self.dtm = make_dtm(ground, grid).data
        count = grid_points(ground, grid.transform, grid.shape, reducer="count")
        self.mask = ndimage.distance_transform_edt(count == 0) <= MASK_CELLS
        self.mask &= np.isfinite(self.dtm)

    def score(self, is_ground: np.ndarray, seconds: float, *, for_dtm=None, noise: float = 0.0) -> dict:
        """Errors of a ground mask; the DTM from ``for_dtm`` (default: all ground), as the method would make it."""
        out = ground_filter_errors(is_ground, self.classes)
        try:
            dtm = make_dtm(self.xyz[is_ground if for_dtm is None else for_dtm], self.grid, noise=noise).data
        except InputError:
            dtm = np.full(self.grid.shape, np.nan)
        sel = self.mask & np.isfinite(dtm)
        diff = (dtm[sel] - self.dtm[sel]) * self.units.vertical
        out.update(
            dtm_rms_m=float(np.sqrt(np.mean(diff**2))) if diff.size else math.nan,
            dtm_mean_m=float(np.mean(diff)) if diff.size else math.nan,
            dtm_cells=int(sel.sum()),
            ground_share_percent=100.0 * float(np.mean(is_ground)),
            seconds=seconds,
            points_per_second=len(is_ground) / seconds,
        )
        return out


# -- driver -------------------------------------------------------------------------


def run_pdal_smrf(path: Path, repeat: int = 1) -> tuple[np.ndarray, float]:
    """PDAL's SMRF with its defaults on the file, the provider's classes cleared first.

    Returns (is_ground, best wall seconds of the whole ``pdal pipeline`` process: read,
    filter and write of an uncompressed LAS the labels are read back from; points keep
    their order through these stages).
    """
    import tempfile

    import laspy

    best, ground = math.inf, None
    with tempfile.TemporaryDirectory(prefix="bench_ground_pdal_") as tmp:
        out = Path(tmp) / "smrf.las"
        spec = Path(tmp) / "smrf.json"
        spec.write_text(json.dumps({"pipeline": [
            str(path),
            {"type": "filters.assign", "value": "Classification = 0"},
            {"type": "filters.smrf"},
            {"type": "writers.las", "filename": str(out), "forward": "all"},
        ]}))
        for _ in range(repeat):
            t = time.perf_counter()
            subprocess.run(_bench.pdal_command("pipeline", str(spec)), check=True, capture_output=True)
            best = min(best, time.perf_counter() - t)
        ground = np.asarray(laspy.read(out).classification) == ASPRS.GROUND
    return ground, best


def bench_file(path: Path, repeat: int, oracle: bool, csf: bool = True, pdal: bool = False, quick: bool = False) -> dict:
    cloud, units = load(path)
    if cloud.classification is None or not np.any(cloud.classification == ASPRS.GROUND):
        raise InputError(f"{path}: no provider ground (class 2) to score against")
    res, _ = choose_resolution(point_spacing(cloud.xyz[:, :2]), units)
    hole_area = DsmConfig().max_hole_area
    hole_area = HOLE_AREA["lidar"][0] if hole_area is None else hole_area  # unset: the pipeline's LiDAR default
    max_cells = int(units.area(hole_area) / res**2)
    grid = make_dsm(cloud, res, max_hole_cells=max_cells)
    ref = Reference(cloud, grid, units)
    classes, counts = np.unique(cloud.classification, return_counts=True)
    record = {
        "file": path.name,
        "points": len(cloud),
        "crs": crs_name(cloud.crs),
        "metres_per_unit": {"horizontal": units.horizontal, "vertical": units.vertical},
        "dsm_cell": res,
        "dtm_rms_cells": int(ref.mask.sum()),
        "classes": {int(c): int(n) for c, n in zip(classes, counts, strict=True)},
        "methods": {},
    }

    result, seconds = run_recon3d(cloud, units, res, repeat)
    noise = result.params["noise"]["value"] / units.vertical
    record["methods"]["recon3d"] = ref.score(result.is_ground, seconds, for_dtm=result.for_dtm, noise=noise) | {
        "params": result.params
    }

    if pdal:
        try:
            is_ground, seconds = run_pdal_smrf(path, repeat)
        except subprocess.CalledProcessError as exc:
            _bench.peer_failed("PDAL", exc.stderr.decode(errors="replace"), quick)
        else:
            if len(is_ground) != len(cloud):
                raise SystemExit(f"{path.name}: PDAL returned {len(is_ground)} points for {len(cloud)}")
            record["methods"]["pdal_smrf"] = ref.score(is_ground, seconds) | {"params": {"filters.smrf": "defaults"}}
    if not csf:
        return record
    lo = cloud.xyz.min(axis=0)
    xyz_m = (cloud.xyz - lo) * np.array([units.horizontal, units.horizontal, units.vertical])
    defaults = csf_defaults()
    is_ground, seconds = run_csf(xyz_m, defaults, repeat)
    record["methods"]["csf"] = ref.score(is_ground, seconds) | {"params": defaults}

    if oracle:
        grid_runs = []
        for values in itertools.product(*ORACLE_GRID.values()):
            params = defaults | dict(zip(ORACLE_GRID, values, strict=True))
            is_ground, seconds = run_csf(xyz_m, params)
            grid_runs.append(ref.score(is_ground, seconds) | {"params": params})
        best = min(grid_runs, key=lambda r: r["total_percent"])
        record["methods"]["csf_oracle"] = best
        record["csf_grid"] = grid_runs
        r, o = record["methods"]["recon3d"], best
        record["ratios_recon3d_over_oracle"] = {
            "total_error": _ratio(r["total_percent"], o["total_percent"]),
            "dtm_rms": _ratio(r["dtm_rms_m"], o["dtm_rms_m"]),
        }
    return record


def _ratio(a: float, b: float) -> float:
    return a / b if b else (math.nan if a == 0 else math.inf)


def print_record(rec: dict) -> None:
    print(
        f"\n{rec['file']}: {rec['points']} points, {rec['crs']}, DSM cell {rec['dsm_cell']} "
        f"CRS units, DTM RMS over {rec['dtm_rms_cells']} cells, scored points "
        f"{rec['methods']['recon3d'].get('n', 0)}"
    )
    print(
        f"  {'method':<11}{'total %':>9}{'type I %':>10}{'type II %':>11}{'kappa':>8}"
        f"{'DTM RMS m':>11}{'pts/s':>11}  params"
    )
    for name, m in rec["methods"].items():
        if name == "recon3d":
            method = m["params"].get("method")
            desc = method.get("value") if isinstance(method, dict) else method
        elif name == "pdal_smrf":
            desc = "filters.smrf defaults (whole pdal process)"
        else:
            p = m["params"]
            desc = (
                f"res {p['cloth_resolution']} m, rigid {p['rigidness']}, "
                f"smooth {p['bSloopSmooth']}"
            )
        print(
            f"  {name:<11}{m['total_percent']:9.2f}{m['type_i_percent']:10.2f}"
            f"{m['type_ii_percent']:11.2f}{m['kappa']:8.3f}{m['dtm_rms_m']:11.3f}"
            f"{m['points_per_second']:11.3g}  {desc}"
        )
    if "pdal_smrf" in rec["methods"]:
        _bench.print_ratios(rec["file"], "PDAL SMRF", rec["methods"]["recon3d"], rec["methods"]["pdal_smrf"], RATIO_KEYS)
    if "csf_oracle" in rec["methods"]:
        _bench.print_ratios(rec["file"], "CSF tuned", rec["methods"]["recon3d"], rec["methods"]["csf_oracle"], RATIO_KEYS)
    if "csf" in rec["methods"]:
        _bench.print_ratios(rec["file"], "CSF", rec["methods"]["recon3d"], rec["methods"]["csf"], RATIO_KEYS)
    if "ratios_recon3d_over_oracle" in rec:
        q = rec["ratios_recon3d_over_oracle"]
        print(f"  recon3d / oracle: total error {q['total_error']:.2f}, DTM RMS {q['dtm_rms']:.2f}")


#: The figures printed beside CSF's, with their ratio.
RATIO_KEYS = [("total_percent", "total error %"), ("type_i_percent", "type I %"), ("type_ii_percent", "type II %"),
              ("dtm_rms_m", "DTM RMS m"), ("points_per_second", "points/s")]


def data_files(folder: Path, quick: bool) -> list[Path]:
    """The .las/.laz files to score: all of ``folder``, or one for ``--quick``."""
    folder = _bench.require(folder, "data folder").resolve()
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".las", ".laz")) if folder.is_dir() else []
    if not files:
        _bench.refuse(f"no .las/.laz files in {folder}")
    if quick:
        files = [p for p in files if p.name == QUICK_FILE] or [min(files, key=lambda p: p.stat().st_size)]
    return files


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--data", type=Path, default=DATA, help="folder of .las/.laz files (default: %(default)s)"
    )
    parser.add_argument(
        "--json", type=Path, help="write every number (and the whole CSF grid) here"
    )
    parser.add_argument(
        "--repeat", type=int, default=3, help="timed runs of recon3d and CSF default; best kept"
    )
    parser.add_argument("--no-oracle", action="store_true", help="skip the CSF parameter grid")
    parser.add_argument("--no-pdal", action="store_true", help="run without PDAL's SMRF")
    _bench.add_quick(parser)
    args = parser.parse_args()
    if args.quick:
        args.repeat, args.no_oracle = 1, True

    files = data_files(args.data, args.quick)
    pdal = _bench.use_pdal(args.no_pdal, args.quick)
    csf = have_csf()
    if not csf:
        _bench.peer_missing("CSF", CSF_INSTALL, args.quick)
    t0 = time.perf_counter()
    records = []
    for path in files:
        t = time.perf_counter()
        rec = bench_file(path, max(args.repeat, 1), not args.no_oracle and csf, csf, pdal, args.quick)
        rec["wall_seconds"] = time.perf_counter() - t
        print_record(rec)
        records.append(rec)
    total = time.perf_counter() - t0
    print(f"\ntotal runtime {total:.1f} s")
    if args.json:
        out = {
            "csf_defaults": csf_defaults() if csf else None,
            "oracle_grid": ORACLE_GRID,
            "mask_cells": MASK_CELLS,
            "files": records,
            "runtime_seconds": total,
        }
        args.json.write_text(json.dumps(out, indent=2, default=_jsonable))


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


if __name__ == "__main__":
    _bench.guard(main)
