"""Rendering the city model back into a DSM on the product grid."""

from __future__ import annotations

import numpy as np

from recon3d.core.city import CityModel
from recon3d.core.raster import Raster

__all__ = ["model_dsm"]


def model_dsm(city: CityModel, dtm: Raster, *, lod: str | None = None) -> Raster:
    """The DTM with every building solid on top of it, as a DSM on the DTM's grid.

    Vertical rays are cast through each cell centre (Open3D ``RaycastingScene``, CPU)
    against the solids of the highest available LoD (or ``lod``); the first hit from
    above is the model surface, and cells with no hit keep the terrain height.

    Parameters
    ----------
    city : CityModel
    dtm : Raster
    lod : str, optional

    Returns
    -------
    Raster
        (rows, cols) float32 model DSM.
    """
    import open3d as o3d

    meshes = []
    for b in city:
        key = lod if lod in b.solids else max(b.solids, default=None, key=float)
        if key is not None:
            meshes.append(b.solids[key].to_trimesh())
    out = dtm.data.astype(np.float64).copy()
    if not meshes:
        return dtm.like(out, product="model DSM")
    vertices = np.concatenate([m.vertices for m in meshes])
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
    )
    x, y = dtm.cell_centers()
    gx, gy = np.meshgrid(x, y)
    origin = np.asarray(city.frame.origin)
    top = float(vertices[:, 2].max()) + 10.0
    rays = np.zeros((gx.size, 6), np.float32)
    rays[:, 0] = gx.ravel() - origin[0]
    rays[:, 1] = gy.ravel() - origin[1]
    rays[:, 2] = top
    rays[:, 5] = -1.0
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t_hit)
    z = (top - t_hit + origin[2]).reshape(out.shape)
    hit = hit.reshape(out.shape)
    out[hit] = np.where(np.isfinite(out[hit]), np.maximum(out[hit], z[hit]), z[hit])
    return dtm.like(out, product="model DSM", method="building solids ray-cast over the DTM")
