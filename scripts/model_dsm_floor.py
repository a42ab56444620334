"""How close any city model can come to the measured DSM: the sampling floor.

The measured DSM takes the highest LiDAR point in each cell, so its value in a cell a
wall crosses depends on whether a point happened to land on the roof side, and on a
steep roof on where the highest point fell. A model DSM rendered from solids cannot
know that. This script runs `recon3d run` on a LiDAR file and compares, on the
report's building cells (``model_check_cells``):

1. the report's number: model_dsm.tif minus dsm.tif;
2. like for like: the model scanned at the cloud's own points (``model_scan``),
   gridded the way the DSM is, minus dsm.tif (the model's error alone);
3. the floor of a perfect model: model_dsm.tif minus that scan of the model, i.e.
   what the report would say if the model were exactly the scanned city;
4. the irreducible floor: the scan repeated with each cell's points at random
   positions inside it; the spread of the highest point per cell is what no
   rendering can predict.

Each line splits into the report's cells "inside roofs" (wholly under the model's
roofs, crossed by no wall) and the others (cells an outer wall, a party wall or a step
between roof parts crosses, or the outline's neighbours).

    .venv/bin/python scripts/model_dsm_floor.py [LAZ] [--crs EPSG:7415] [--draws 12]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from recon3d.buildings.detect import vegetation_mask
from recon3d.core.geo import parse_crs
from recon3d.pipeline.run import run
from recon3d.quality.evaluate import model_check_cells
from recon3d.quality.rasterize import surface_at, wall_cells
from recon3d.terrain.dsm import grid_points, surface_points

DELFT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lidar" / "delft_ahn3_strip.laz"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("laz", nargs="?", type=Path, default=DELFT, help="a LiDAR file (default: the Delft strip)")
    parser.add_argument("--crs", default=None, help="CRS when the file does not say (Delft: EPSG:7415)")
    parser.add_argument("--draws", type=int, default=12, help="random scans for the irreducible floor")
    args = parser.parse_args()
    crs = args.crs or ("EPSG:7415" if args.laz == DELFT else None)
    with tempfile.TemporaryDirectory() as tmp:
        s = run(args.laz, Path(tmp) / "out", crs=parse_crs(crs) if crs else None, keep_points=True)
    cells = model_check_cells(s.dsm, s.model_dsm, s.labels, vegetation_mask(s.vegetation_share), s.dsm_filled)
    inside = cells & (s.roof_cover >= 1.0) & ~wall_cells(s.city, s.dsm)
    scanned = s.model_scan.data
    rows = {
        "report: model DSM - DSM": s.model_dsm.data - s.dsm.data,
        "like for like: model scan - DSM": scanned - s.dsm.data,
        "perfect model: model DSM - model scan": s.model_dsm.data - scanned,
        "irreducible: spread of random scans": _random_scans(s, args.draws),
    }
    print(f"{args.laz.name}: {int(cells.sum())} building cells, {int(inside.sum())} inside roofs (wholly under them, no wall)")
    print(f"{'':42s}{'all':>8s}{'inside roofs':>14s}{'others':>9s}   (RMS, m)")
    for name, diff in rows.items():
        print(f"{name:42s}" + "".join(f"{_rms(diff, m):{w}.3f}" for m, w in ((cells, 8), (inside, 14), (cells & ~inside, 9))))


def _random_scans(s, draws: int) -> np.ndarray:
    """(rows, cols) standard deviation of the highest point per cell over ``draws``
    scans of the model, each keeping every cell's number of points but placing them
    uniformly at random inside it."""
    grid = s.dsm
    xyz = s.cloud.xyz[surface_points(s.cloud)]
    row, col = grid.rowcol(xyz[:, 0], xyz[:, 1])
    rows, cols = grid.shape
    ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    count = np.bincount(row[ok] * cols + col[ok], minlength=rows * cols)
    r, c = np.divmod(np.repeat(np.arange(rows * cols), count), cols)
    rng = np.random.default_rng(0)
    t = grid.transform
    tops = []
    for _ in range(draws):
        x = t.c + (c + rng.random(len(c))) * t.a
        y = t.f + (r + rng.random(len(r))) * t.e
        z = surface_at(s.city, x, y, s.dtm)
        tops.append(grid_points(np.column_stack([x, y, z]), t, grid.shape, reducer="max"))
    return np.std(tops, axis=0, ddof=1)


def _rms(values: np.ndarray, mask: np.ndarray) -> float:
    v = values[mask & np.isfinite(values)]
    return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")


if __name__ == "__main__":
    main()
