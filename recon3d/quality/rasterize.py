"""Rendering the city model back into a DSM on the product grid."""

from __future__ import annotations

import numpy as np

from recon3d.core.city import CityModel
from recon3d.core.raster import Raster

__all__ = ["model_dsm", "roof_cover"]


def model_dsm(city: CityModel, dtm: Raster, *, lod: str | None = None, samples: int = 3) -> Raster:
    """The DTM with every building solid on top of it, as a DSM on the DTM's grid.

    Vertical rays are cast on a ``samples`` x ``samples`` lattice inside each cell
    (Open3D ``RaycastingScene``, CPU) against the solids of the highest available LoD
    (or ``lod``); a cell takes the highest first hit from above, like the measured
    DSM takes the highest point per cell, and cells with no hit keep the terrain
    height. A single ray through the centre would charge every eave cell whose centre
    falls just outside the footprint with the whole wall height.

    Parameters
    ----------
    city : CityModel
    dtm : Raster
    lod : str, optional
    samples : int
        Rays per cell along each axis (1 = the cell centre only).

    Returns
    -------
    Raster
        (rows, cols) float32 model DSM.
    """
    highest, _ = _cast(city, dtm, lod, samples)
    out = dtm.data.astype(np.float64).copy()
    hit = np.isfinite(highest)
    out[hit] = np.where(np.isfinite(out[hit]), np.maximum(out[hit], highest[hit]), highest[hit])
    return dtm.like(out, product="model DSM", method=f"building solids ray-cast over the DTM, highest of {samples} x {samples} rays per cell")


def roof_cover(city: CityModel, grid: Raster, *, lod: str | None = None, samples: int = 3) -> np.ndarray:
    """(rows, cols) float: the share of each cell's ``samples`` x ``samples`` vertical
    rays that hit a building solid (1 wholly on roofs, 0 off the buildings; in
    between, a cell that a wall crosses)."""
    return _cast(city, grid, lod, samples)[1]


def _cast(city: CityModel, grid: Raster, lod: str | None, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """(highest hit or -inf, share of rays that hit), both (rows, cols), over ``grid``."""
    import open3d as o3d

    highest = np.full(grid.shape, -np.inf)
    hits = np.zeros(grid.shape)
    meshes = []
    for b in city:
        key = lod if lod in b.solids else max(b.solids, default=None, key=float)
        if key is not None:
            meshes.append(b.solids[key].to_trimesh())
    if not meshes:
        return highest, hits
    vertices = np.concatenate([m.vertices for m in meshes])
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
    )
    x, y = grid.cell_centers()
    gx, gy = np.meshgrid(x, y)
    origin = np.asarray(city.frame.origin)
    top = float(vertices[:, 2].max()) + 10.0
    a, e = grid.transform.a, grid.transform.e
    steps = (np.arange(samples) + 0.5) / samples - 0.5  # offsets in cells, centred
    rays = np.zeros((gx.size, 6), np.float32)
    rays[:, 2] = top
    rays[:, 5] = -1.0
    for sy in steps:
        for sx in steps:
            rays[:, 0] = gx.ravel() + sx * a - origin[0]
            rays[:, 1] = gy.ravel() + sy * e - origin[1]
            t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
            z = (top - t_hit + origin[2]).reshape(grid.shape)  # -inf where no hit
            hit = np.isfinite(z)
            np.maximum(highest, z, out=highest, where=hit)
            hits += hit
    return highest, hits / samples**2
