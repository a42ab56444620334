"""Rendering the city model back into a DSM on the product grid."""

from __future__ import annotations

import numpy as np

from recon3d.core.city import CityModel
from recon3d.core.raster import Raster

__all__ = ["model_dsm", "model_tags", "ray_top", "render", "surface_at", "wall_cells"]


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
    return render(city, dtm, lod=lod, samples=samples)[0]


def render(city: CityModel, dtm: Raster, *, lod: str | None = None, samples: int = 3,
           top: float | None = None) -> tuple[Raster, np.ndarray]:
    """:func:`model_dsm` and, from the same rays, how much of each cell the roofs cover.

    ``dtm`` may be a window of a larger grid, and ``city`` the buildings over it: with
    the whole city's ``top`` (:func:`ray_top`) each cell gets the heights the whole
    city gives it, to the last bit.

    Returns
    -------
    model : Raster
        (rows, cols) float32 model DSM on the DTM's grid.
    cover : (rows, cols) float
        Share of each cell's ``samples`` x ``samples`` rays that hit a building solid:
        1 wholly on roofs, 0 off the buildings, in between a cell that a wall crosses.
    """
    highest, cover = _lattice(city, dtm, lod, samples, top)
    out = dtm.data.astype(np.float64).copy()
    hit = np.isfinite(highest)
    out[hit] = np.where(np.isfinite(out[hit]), np.maximum(out[hit], highest[hit]), highest[hit])
    return dtm.like(out, **model_tags(samples)), cover


def model_tags(samples: int = 3) -> dict[str, str]:
    """The tags of :func:`render`'s model DSM."""
    return {"product": "model DSM",
            "method": f"building solids ray-cast over the DTM, highest of {samples} x {samples} rays per cell"}


def surface_at(
    city: CityModel, x: np.ndarray, y: np.ndarray, dtm: Raster, *, lod: str | None = None, top: float | None = None
) -> np.ndarray:
    """(n,) height of the model's surface at world positions: the highest solid
    above each (x, y), or the DTM (bilinear) where no solid stands.

    Sampled at a cloud's own points and gridded the way the DSM is, this is the DSM a
    scan of the model would give: the like-for-like counterpart of the measured DSM.
    ``top`` (:func:`ray_top`) is the local height the rays start from; a tile that
    holds some of a city's buildings passes the whole city's, so that its heights are
    the ones the whole city gives to the last bit.
    """
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    z = _Scene(city, lod, top).highest(x, y)
    return np.where(np.isfinite(z), z, dtm.sample(x, y, bilinear=True))


def ray_top(city: CityModel, lod: str | None = None) -> float:
    """Local height (the city's frame) the vertical rays start from: 10 above the highest solid."""
    tops = [float(m.vertices[:, 2].max()) for m in _meshes(city, lod) if len(m.vertices)]
    return max(tops, default=0.0) + 10.0


def wall_cells(city: CityModel, grid: Raster, *, lod: str | None = None) -> np.ndarray:
    """(rows, cols) bool: the cells of ``grid`` that a wall of the model crosses.

    Every ``WallSurface`` of the solid :func:`render` casts against (``lod``, else the
    highest): the outer walls, the party walls between the buildings of a block and the
    steps between the parts of one roof. Such a cell holds two heights a wall apart,
    and its measured DSM takes the one its points happened to fall on.
    """
    import rasterio.features
    import shapely

    rings, owner = [], []
    for solid in _solids(city, lod):
        for surface, kind in zip(solid.surfaces, solid.semantics, strict=True):
            if kind == "WallSurface":
                ring = solid.vertices[surface[0], :2]
                rings.append(np.vstack([ring, ring[:1]]))
                owner.append(np.full(len(ring) + 1, len(owner)))
    if not rings:
        return np.zeros(grid.shape, bool)
    traces = shapely.linestrings(np.vstack(rings) + np.asarray(city.frame.origin[:2]), indices=np.concatenate(owner))
    burnt = rasterio.features.rasterize(traces, out_shape=grid.shape, transform=grid.transform, all_touched=True,
                                        dtype=np.uint8)
    return burnt.astype(bool)


def _solids(city: CityModel, lod: str | None) -> list:
    """One solid per building: ``lod``, else its highest."""
    solids = []
    for b in city:
        key = lod if lod in b.solids else max(b.solids, default=None, key=float)
        if key is not None:
            solids.append(b.solids[key])
    return solids


def _meshes(city: CityModel, lod: str | None) -> list:
    """The triangles (:class:`~recon3d.core.mesh.SolidMesh`) of one solid per building: ``lod``, else its highest."""
    return [solid.mesh() for solid in _solids(city, lod)]


class _Scene:
    """The solids of one LoD per building in an Open3D ray-casting scene (local frame)."""

    def __init__(self, city: CityModel, lod: str | None, top: float | None = None) -> None:
        from recon3d.core.o3d import open3d

        o3d = open3d()
        meshes = _meshes(city, lod)
        self.scene = None
        if not meshes:
            return
        vertices = np.concatenate([m.vertices for m in meshes])
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)])
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
        )
        self.origin = np.asarray(city.frame.origin, np.float64)
        self.top = float(vertices[:, 2].max()) + 10.0 if top is None else float(top)

    def highest(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n,) world height of the first hit of a vertical ray from above, -inf where none."""
        from recon3d.core.o3d import open3d

        o3d = open3d()
        if self.scene is None:
            return np.full(np.shape(x), -np.inf)
        rays = np.zeros((np.size(x), 6), np.float32)
        rays[:, 0] = np.ravel(x) - self.origin[0]
        rays[:, 1] = np.ravel(y) - self.origin[1]
        rays[:, 2] = self.top
        rays[:, 5] = -1.0
        t_hit = self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
        return (self.top - t_hit + self.origin[2]).reshape(np.shape(x))  # -inf where no hit


#: Rows of cells whose rays are cast at a time: bounds the rays' memory (a strip of a
#: 4,000-column grid at 3 x 3 rays per cell is about 60 MB).
STRIP_ROWS = 256


def _lattice(city: CityModel, grid: Raster, lod: str | None, samples: int,
             top: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(highest hit or -inf, share of rays that hit), both (rows, cols), over ``grid``,
    cast :data:`STRIP_ROWS` rows at a time."""
    scene = _Scene(city, lod, top)
    highest = np.full(grid.shape, -np.inf)
    hits = np.zeros(grid.shape)
    x, y = grid.cell_centers()
    a, e = grid.transform.a, grid.transform.e
    steps = (np.arange(samples) + 0.5) / samples - 0.5  # offsets in cells, centred
    for start in range(0, grid.shape[0], STRIP_ROWS):
        rows = slice(start, start + STRIP_ROWS)
        gx, gy = np.meshgrid(x, y[rows])
        top, count = highest[rows], hits[rows]
        for sy in steps:
            for sx in steps:
                z = scene.highest(gx + sx * a, gy + sy * e)
                hit = np.isfinite(z)
                np.maximum(top, z, out=top, where=hit)
                count += hit
    return highest, hits / samples**2
