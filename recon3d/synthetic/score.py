"""Scoring stereo products against a synthetic scene's exact truth.

The measures of the frame-stereo targets, restricted to the *common area*: the truth
cells whose top surface at least two images have in frame (``truth/views.tif``).

- ``coverage``: share of the common area where the DSM has a value; ``observed``: share
  where it holds a matched (not filled-in) observation, when the caller knows which;
  ``visible``: share whose top surface two images see unhidden (the most matching can
  observe: the rest is occluded in all but one view).
- ``dsm_rms_tolerant``: RMS of the DSM error where any height between the lowest and the
  highest truth surface within the product cell counts as exact (a wall crossing a cell
  is no error; a roof spilled onto the street is). The truth range comes from vertical
  rays cast at 5 x 5 points per product cell, its corners and edges included (a roof
  that only grazes a cell still counts). ``dsm_within_1m``: plain error (truth at the
  cell centre) within +-1 m. ``dsm_nmad``: NMAD of the plain error.
- ``ground_rms`` (DTM) and ``roof_rms`` (DSM): the scene's check points inside the
  common area, one per roof part.
- ``footprint_completeness`` and ``footprint_correctness``: area shares of the truth
  and the detected footprints, inside the common area. ``object_completeness``: share
  of the truth buildings at least half inside the common area that detections cover by
  half or more; ``object_correctness``: share of the detections at least half inside
  it that lie by half or more on truth buildings (the ISPRS rule).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import shapely
from rasterio.features import rasterize

from recon3d.core.raster import Raster
from recon3d.io.geotiff import read_raster
from recon3d.synthetic.city import SyntheticCity

__all__ = ["scene_cameras", "score_stereo", "tolerant_error", "truth_range", "visible_cells"]


def truth_range(city: SyntheticCity, grid: Raster, cells: np.ndarray, samples: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest truth surface within each product cell, (rows, cols) float32 each.

    Vertical rays at ``samples`` x ``samples`` points spread evenly over each cell from
    edge to edge, cast only where ``cells`` is True (NaN elsewhere).
    """
    from recon3d.core.o3d import open3d

    o3d = open3d()
    rows, cols = np.nonzero(cells)
    t = grid.transform
    off = np.linspace(0.0, 1.0, samples) if samples > 1 else np.array([0.5])
    du, dv = (a.ravel() for a in np.meshgrid(off, off))
    lo = np.full(grid.shape, np.nan, np.float32)
    hi = np.full(grid.shape, np.nan, np.float32)
    ox, oy, oz = city.origin
    top = float(city.vertices[:, 2].max()) + 10.0
    chunk = 200_000
    for start in range(0, len(rows), chunk):
        r, c = rows[start:start + chunk], cols[start:start + chunk]
        x = t.c + (c[:, None] + du) * t.a + (r[:, None] + dv) * t.b - ox
        y = t.f + (c[:, None] + du) * t.d + (r[:, None] + dv) * t.e - oy
        rays = np.zeros((x.size, 6), np.float32)
        rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = x.ravel(), y.ravel(), top, -1.0
        hit = city.raycaster().cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(x.shape)
        z = np.where(np.isfinite(hit), top - hit + oz, np.nan)
        lo[r, c] = np.nanmin(z, axis=1)
        hi[r, c] = np.nanmax(z, axis=1)
    return lo, hi


def tolerant_error(city: SyntheticCity, dsm: Raster, cells: np.ndarray) -> np.ndarray:
    """(rows, cols) DSM error where any height between the lowest and the highest truth
    surface within the cell counts as exact (:func:`truth_range`): 0 inside that range,
    the signed distance to it outside. NaN outside ``cells``, where the DSM is empty and
    where the truth has no surface."""
    cells = cells & np.isfinite(dsm.data)
    lo, hi = truth_range(city, dsm, cells)
    v = dsm.data
    error = np.where(v > hi, v - hi, np.where(v < lo, v - lo, 0.0))
    return np.where(cells & np.isfinite(lo), error, np.nan)


def score_stereo(
    scene: str | Path,
    dsm: Raster,
    *,
    dtm: Raster | None = None,
    footprints: list[shapely.Polygon] | None = None,
    observed: np.ndarray | None = None,
    city: SyntheticCity | None = None,
) -> dict:
    """The frame-stereo measures of a DSM (and DTM, footprints) against a scene's truth.

    Parameters
    ----------
    scene : path
        A scene folder written by :mod:`recon3d.synthetic.scene` (with ``truth/``).
    dsm : Raster
        The product DSM (world CRS of the scene).
    dtm : Raster, optional
    footprints : list of shapely.Polygon, optional
        Detected building outlines, world coordinates.
    observed : (rows, cols) bool, optional
        DSM cells holding a matched observation (not filled in).
    city : SyntheticCity, optional
        The scene's city, rebuilt from ``truth/scene.json`` when not given.

    Returns
    -------
    dict
        The measures of the module docstring (percentages, metres), plus ``common_cells``.
    """
    from recon3d.synthetic.scene import scene_city

    truth = Path(scene) / "truth"
    city = city or scene_city(scene)
    views = read_raster(truth / "views.tif")
    common = _on_grid(views, dsm) >= 2
    out: dict = {"common_cells": int(common.sum())}
    if not common.any():
        return out
    value = dsm.data
    finite = np.isfinite(value)
    out["coverage"] = _pct(finite[common])
    if observed is not None:
        out["observed"] = _pct(observed[common])
    out["visible"] = _visible_share(scene, city, dsm, common)
    error = tolerant_error(city, dsm, common)
    exact = _on_grid(read_raster(truth / "dsm.tif"), dsm)
    cells = np.isfinite(error)
    tolerant = error[cells]
    plain = (value - exact)[cells & np.isfinite(exact)]
    out["dsm_rms_tolerant"] = _rms(tolerant)
    out["dsm_within_1m"] = _pct(np.abs(plain) <= 1.0)
    out["dsm_nmad"] = round(float(1.4826 * np.median(np.abs(plain - np.median(plain)))), 3) if plain.size else None
    out["dsm_median"] = round(float(np.median(plain)), 3) if plain.size else None
    xyz, kinds = _checkpoints(truth / "checkpoints.csv")
    inside = _sample(views, xyz) >= 2
    ground, roof = inside & (kinds == "ground"), inside & (kinds == "roof")
    if dtm is not None:
        out["ground_rms"] = _rms(dtm.sample(xyz[ground, 0], xyz[ground, 1]) - xyz[ground, 2])
        out["ground_n"] = int(ground.sum())
    out["roof_rms"] = _rms(dsm.sample(xyz[roof, 0], xyz[roof, 1], bilinear=False) - xyz[roof, 2])
    out["roof_n"] = int(roof.sum())
    if footprints is not None:
        out.update(_footprint_scores(city, footprints, dsm, common))
    return out


def _visible_share(scene, city: SyntheticCity, grid: Raster, common: np.ndarray) -> float:
    """Percent of the common cells whose top surface at least two cameras see unhidden."""
    return _pct(visible_cells(scene, city, grid, common)[common])


def visible_cells(scene, city: SyntheticCity, grid: Raster, cells: np.ndarray) -> np.ndarray:
    """(rows, cols) bool: the ``cells`` whose top surface (at the cell centre) at least
    two cameras of the scene see unhidden, so that stereo can measure it."""
    from recon3d.synthetic.render import visible

    cameras = scene_cameras(scene, city)
    rows, cols = np.nonzero(cells)
    lo, hi = truth_range(city, grid, cells, samples=1)  # the cell centre's surface
    x, y = grid.cell_centers()
    local = np.column_stack([x[cols], y[rows], hi[rows, cols]]) - np.asarray(city.origin)
    count = np.zeros(len(local), int)
    for cam in cameras:
        # the COLMAP cameras are in model = local coordinates; visible() wants the renderer's convention
        count += visible(city, cam, local, tol=0.05)
    out = np.zeros(grid.shape, bool)
    out[rows, cols] = count >= 2
    return out


def scene_cameras(scene: str | Path, city: SyntheticCity) -> list:
    """The renderer's cameras of a scene folder (local coordinates of ``city``).

    Frame scenes are read back from their COLMAP model; satellite scenes rebuilt from
    the pair's parameters in ``truth/scene.json``.
    """
    import json

    record = json.loads((Path(scene) / "truth" / "scene.json").read_text(encoding="utf-8"))
    if record.get("generator") == "recon3d.synthetic.satellite":
        from recon3d.synthetic.satellite import SatelliteSpec, satellite_pair

        spec = record["spec"]
        spec["centre_lonlat"] = tuple(spec["centre_lonlat"])
        return list(satellite_pair(SatelliteSpec(**spec), city))
    from recon3d.io.colmap import read_scene

    return [_renderer_camera(cam) for cam in read_scene(scene).cameras]


def _renderer_camera(cam):
    from recon3d.synthetic.render import PinholeCamera

    K = cam.K.copy()
    K[:2, 2] += 0.5  # OpenCV to COLMAP pixel centres
    return PinholeCamera(K, cam.R, cam.t, cam.width, cam.height, cam.name, tuple(cam.dist[:4]))


def _footprint_scores(city: SyntheticCity, detected: list, grid: Raster, common: np.ndarray) -> dict:
    def mask(polygons):
        shapes = [(p, 1) for p in polygons if p is not None and not p.is_empty]
        if not shapes:
            return np.zeros(grid.shape, bool)
        return rasterize(shapes, out_shape=grid.shape, transform=grid.transform).astype(bool) & common

    from recon3d.quality.buildings import covered_shares

    truth = mask([b.footprint for b in city.buildings])
    found = mask(detected)
    both = (truth & found).sum()
    everything = [b.footprint for b in city.buildings]
    reference = [p for p in everything if _share_inside(p, grid, common) >= 0.5]
    detected = [p for p in detected if p is not None and not p.is_empty and _share_inside(p, grid, common) >= 0.5]
    n_found = int((covered_shares(reference, detected) >= 0.5).sum()) if detected else 0
    n_correct = int((covered_shares(detected, everything) >= 0.5).sum()) if everything else 0
    return {
        "footprint_completeness": round(100.0 * both / max(1, truth.sum()), 2),
        "footprint_correctness": round(100.0 * both / max(1, found.sum()), 2),
        "truth_buildings": int(sum(1 for b in city.buildings if (mask([b.footprint])).any())),
        "object_completeness": round(100.0 * n_found / len(reference), 2) if reference else None,
        "object_correctness": round(100.0 * n_correct / len(detected), 2) if detected else None,
    }


def _share_inside(polygon, grid: Raster, common: np.ndarray) -> float:
    """Share of the cells of ``polygon`` that lie in the common area (0 without cells)."""
    cells = rasterize([(polygon, 1)], out_shape=grid.shape, transform=grid.transform).astype(bool)
    return float(common[cells].mean()) if cells.any() else 0.0


def _on_grid(source: Raster, grid: Raster) -> np.ndarray:
    """``source`` sampled at the cell centres of ``grid`` (nearest cell)."""
    rows, cols = grid.shape
    c, r = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    t = grid.transform
    x, y = t.c + c * t.a + r * t.b, t.f + c * t.d + r * t.e
    return source.sample(x.ravel(), y.ravel(), bilinear=False).reshape(rows, cols)


def _sample(raster: Raster, xyz: np.ndarray) -> np.ndarray:
    return np.nan_to_num(raster.sample(xyz[:, 0], xyz[:, 1], bilinear=False))


def _checkpoints(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with path.open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    xyz = np.array([[float(r["x"]), float(r["y"]), float(r["z"])] for r in rows]).reshape(-1, 3)
    return xyz, np.array([r["kind"] for r in rows])


def _pct(mask: np.ndarray) -> float:
    return round(100.0 * float(np.mean(mask)), 2) if np.size(mask) else float("nan")


def _rms(errors: np.ndarray) -> float | None:
    e = np.asarray(errors, np.float64)
    e = e[np.isfinite(e)]
    return round(float(np.sqrt(np.mean(e**2))), 3) if e.size else None
