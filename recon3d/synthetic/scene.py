"""Write a synthetic city as a frame-stereo scene folder with its ground truth.

Layout (the input part is what ``recon3d run`` reads; ``truth/`` is for evaluation)::

    images/left.png images/right.png    RGB, 8 bit
    sparse/                              COLMAP text model (cameras, images, points3D,
                                         rigs, frames); model = local coordinates
    georef.json                          {"crs": "EPSG:32631", "offset": [x0, y0, z0]}
    truth/dsm.tif truth/dtm.tif          GeoTIFF float32, world CRS and coordinates
    truth/footprints.geojson             id, plan, roof_type, ground_z, eave_z, ridge_z, ...
    truth/buildings.city.json            CityJSON 2.0, LoD1 and LoD2.2 solids
    truth/checkpoints.csv                x,y,z,id,kind (ground, roof), world coordinates
    truth/trees.csv                      x,y,ground_z,top_z,crown_radius,crown,id
    truth/views.tif                      how many images see each cell's top surface point
    truth/coarse_dem.tif                 the terrain on 20 m cells with 0.5 m of noise (a
                                         national DTM's kind), for vector-constrained matching
    truth/spot_heights.csv               x,y,z of surveyed ground points on a 50 m grid
    truth/scene.json                     parameters of the scene (seed, gsd, cameras...)

:func:`write_scene` renders the demo's kind of scene: a city that fits in every image,
seen by convergent cameras. :func:`write_block_scene` renders a survey of the family in
:mod:`recon3d.synthetic.family`: nadir images in strips over a city sized to the block,
each image seeing part of it, every sparse point seen by two images or more.

Every file is a deterministic function of the parameters (same seed, same bytes).
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from recon3d.buildings.lod import clean_footprint, lod1_solid
from recon3d.core.city import Building, CityModel
from recon3d.core.geo import parse_crs
from recon3d.core.raster import Raster, grid_for_bounds
from recon3d.io import atomic_path
from recon3d.synthetic.city import (
    SyntheticCity,
    cell_centres,
    checkpoints,
    make_city,
    nice_cell_size,
    row_blocks,
    truth_dsm,
    truth_dtm,
)
from recon3d.synthetic.family import SceneSpec
from recon3d.synthetic.render import (
    Lighting,
    PinholeCamera,
    Render,
    check_coverage,
    ground_footprint,
    render_pair,
    sparse_points,
    stereo_cameras,
)

log = logging.getLogger(__name__)

__all__ = ["SceneInfo", "block_city", "city_model", "scene_city", "views", "write_block_scene", "write_colmap", "write_scene"]

#: CityJSON ``referenceDate`` of the truth (fixed, so the file is byte-identical per seed).
_REFERENCE_DATE = "2024-01-01"


@dataclass
class SceneInfo:
    """What :func:`write_scene` wrote.

    Attributes
    ----------
    folder : Path
    city : SyntheticCity
    cameras : tuple of PinholeCamera
        In local (model) coordinates.
    renders : list of Render
        Images and the surface point seen through every pixel centre.
    sparse_xyz : (n, 3) float64
        Local coordinates of the COLMAP model's 3-D points.
    sparse_uv : (n_images, n, 2) float64
        Their projections in each image (COLMAP pixel convention).
    sparse_seen : (n_images, n) bool
        Which images observe each point (its COLMAP track).
    cell_size : float
        Cell size of the truth rasters.
    timings : dict of str to float
        Seconds per step ("city", "render", "truth", "write").
    spec : SceneSpec or None
        The survey, for scenes of the family.
    """

    folder: Path
    city: SyntheticCity
    cameras: tuple[PinholeCamera, ...]
    renders: list[Render]
    sparse_xyz: np.ndarray
    sparse_uv: np.ndarray
    sparse_seen: np.ndarray
    cell_size: float
    timings: dict[str, float] = field(default_factory=dict)
    spec: SceneSpec | None = None


def write_scene(
    folder: str | Path,
    *,
    seed: int = 0,
    size: float = 150.0,
    gsd: float = 0.25,
    image_size: tuple[int, int] = (1000, 750),
    base_to_height: float = 0.4,
    n_sparse: int = 400,
    n_buildings: int | None = None,
    lighting: Lighting = Lighting(),
    n_images: int = 2,
) -> SceneInfo:
    """Build a city, render an aerial stereo pair (or strip) and write the scene folder.

    Parameters
    ----------
    folder : str or Path
        Created if needed; files of an earlier scene there are replaced.
    seed : int
    size : float
        Side of the city in metres; it must fit in every image.
    gsd : float
        Ground sample distance in metres (nadir, at the flying height); the truth
        rasters use it rounded to 1, 2, 2.5 or 5 times a power of ten.
    image_size : (width, height)
    base_to_height : float
    n_sparse : int
        Number of 3-D points of the COLMAP model (surface points seen in every image).
    n_buildings : int, optional
        See :func:`~recon3d.synthetic.city.make_city`.
    lighting : Lighting
    n_images : int
        Images along the flight line, the first and last ``base_to_height`` apart
        (see :func:`~recon3d.synthetic.render.stereo_cameras`).

    Returns
    -------
    SceneInfo

    Raises
    ------
    ValueError
        The city does not fit in the images (see
        :func:`~recon3d.synthetic.render.check_coverage`).
    """
    folder = Path(folder)
    width, height = (int(v) for v in image_size)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    margin = _terrain_margin(size, gsd, width, height, base_to_height, seed, n_images)
    city = make_city(seed, size=size, n_buildings=n_buildings, margin=margin)
    centre = np.array([size / 2])
    target = np.array([size / 2, size / 2, float(city.terrain.height(centre, centre)[0])])
    cameras = stereo_cameras(
        target, gsd=gsd, width=width, height=height, base_to_height=base_to_height, seed=seed, n_images=n_images
    )
    check_coverage(city, cameras)
    timings["city"] = time.perf_counter() - start
    record = {"base_to_height": base_to_height}
    return _write(folder, city, cameras, gsd, lighting, n_sparse, None, record, timings, seed)


def write_block_scene(folder: str | Path, spec: SceneSpec, *, lighting: Lighting = Lighting()) -> SceneInfo:
    """Render a survey of the family (:class:`~recon3d.synthetic.family.SceneSpec`) to a scene folder.

    The city (:func:`block_city`) follows the spec's terrain, layout and trees.

    Parameters
    ----------
    folder : str or Path
        Created if needed; files of an earlier scene there are replaced.
    spec : SceneSpec
    lighting : Lighting

    Returns
    -------
    SceneInfo
    """
    timings: dict[str, float] = {}
    start = time.perf_counter()
    city, cameras = block_city(spec)
    timings["city"] = time.perf_counter() - start
    record = {"base_to_height": spec.base_to_height, "spec": spec.to_dict()}
    return _write(folder, city, cameras, spec.gsd, lighting, spec.n_sparse, 2, record, timings, spec.seed, spec)


def scene_city(folder: str | Path) -> SyntheticCity:
    """The city of a scene folder written by this module, rebuilt from ``truth/scene.json``."""
    record = json.loads((Path(folder) / "truth" / "scene.json").read_text(encoding="utf-8"))
    return make_city(**record["city"])


def block_city(spec: SceneSpec) -> tuple[SyntheticCity, tuple[PinholeCamera, ...]]:
    """The city of a survey and its cameras (local coordinates), without rendering.

    The city is a square centred under the block, just large enough to hold every
    image's ground footprint; its terrain reaches beyond, so every pixel sees ground.
    """
    nominal = spec.cameras(np.array([0.0, 0.0, 50.0]))
    reach = max(float(np.abs(ground_footprint(c, 50.0)).max()) for c in nominal)
    size = float(math.ceil((2.0 * reach + 10.0) / 10.0) * 10.0)
    low = max(float(np.abs(ground_footprint(c, -60.0)).max()) for c in nominal)
    city = make_city(
        spec.seed, size=size, margin=low - size / 2 + 30.0,
        terrain=spec.terrain, layout=spec.layout, trees=spec.trees,
    )
    centre = np.array([size / 2])
    target = np.array([size / 2, size / 2, float(city.terrain.height(centre, centre)[0])])
    return city, spec.cameras(target)


def _write(
    folder, city, cameras, gsd, lighting, n_sparse, min_views, record, timings, seed, spec=None
) -> SceneInfo:
    """Render, then write the images, the COLMAP model, georef.json and truth/."""
    folder = Path(folder)
    width, height = cameras[0].width, cameras[0].height
    start = time.perf_counter()
    renders = render_pair(city, cameras, lighting=lighting, seed=seed)
    xyz, uv, seen = sparse_points(city, cameras, n_sparse, seed=seed, min_views=min_views)
    timings["render"] = time.perf_counter() - start

    start = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    for r in renders:
        _write_png(folder / "images" / r.camera.name, r.image)
    first = np.argmax(seen, axis=0)  # colour of each point from the first image that sees it
    rows = np.clip(uv[first, np.arange(len(xyz)), 1].astype(int), 0, height - 1)
    cols = np.clip(uv[first, np.arange(len(xyz)), 0].astype(int), 0, width - 1)
    images = np.stack([r.image for r in renders])
    colours = images[first, rows, cols]
    write_colmap(folder / "sparse", cameras, xyz, uv, colours, seen=seen)
    _write_json(folder / "georef.json", {"crs": city.crs, "offset": list(city.origin)})
    timings["write"] = time.perf_counter() - start

    start = time.perf_counter()
    cell = nice_cell_size(gsd)
    _write_truth(folder / "truth", city, cell, cameras)
    record = {**_scene_record(city, cameras, gsd, cell, lighting, len(xyz)), **record}
    _write_json(folder / "truth" / "scene.json", record)
    timings["truth"] = time.perf_counter() - start
    log.info(
        "synthetic scene %s: %d buildings, %d trees, %d images, %d sparse points; %s",
        folder, len(city.buildings), len(city.trees), len(cameras), len(xyz),
        ", ".join(f"{k} {v:.2f} s" for k, v in timings.items()),
    )
    return SceneInfo(folder, city, cameras, renders, xyz, uv, seen, cell, timings, spec)


def _terrain_margin(
    size: float, gsd: float, width: int, height: int, b_h: float, seed: int, n_images: int = 2
) -> float:
    """How far the terrain must extend beyond the city so every pixel sees ground.

    The image corners' rays of a nominal pair are intersected with a plane 15 m
    below the target (the terrain relief is a few metres).
    """
    target = np.array([size / 2, size / 2, 0.0])
    cams = stereo_cameras(
        target, gsd=gsd, width=width, height=height, base_to_height=b_h, seed=seed, n_images=n_images
    )
    reach = 0.0
    for cam in cams:
        w, h = cam.width, cam.height
        corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], float)
        d = cam.rays(corners)
        t = (cam.center[2] + 15.0) / -d[:, 2]
        ground = cam.center + t[:, None] * d
        reach = max(reach, float(np.abs(ground[:, :2] - size / 2).max()))
    return max(20.0, reach - size / 2 + 20.0)


def write_colmap(
    folder: str | Path,
    cameras: tuple[PinholeCamera, ...],
    xyz: np.ndarray,
    uv: np.ndarray,
    colours: np.ndarray | None = None,
    *,
    seen: np.ndarray | None = None,
) -> None:
    """Write a COLMAP text model: one camera per image (PINHOLE, or OPENCV with lens
    distortion), posed images, 3-D points.

    Parameters
    ----------
    folder : str or Path
        Replaced as a whole (written beside, then renamed).
    cameras : sequence of PinholeCamera
        Image ids are 1, 2, ... in this order, camera ids likewise.
    xyz : (n, 3) float64
        Model coordinates of the points.
    uv : (len(cameras), n, 2) float64
        Observation of every point in every image (COLMAP pixel convention).
    colours : (n, 3) uint8, optional
    seen : (len(cameras), n) bool, optional
        Which images observe each point (its track); default every image.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    for k, cam in enumerate(cameras, start=1):
        camera = pycolmap.Camera(
            model=getattr(cam, "model", "PINHOLE"), width=cam.width, height=cam.height, params=cam.params,
            camera_id=k,
        )
        rec.add_camera_with_trivial_rig(camera)
        keypoints = np.asarray(uv[k - 1], np.float64)
        image = pycolmap.Image(name=cam.name, keypoints=keypoints, camera_id=k, image_id=k)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t.reshape(3, 1))
        rec.add_image_with_trivial_frame(image, pose)
    if colours is None:
        colours = np.full((len(xyz), 3), 128, np.uint8)
    if seen is None:
        seen = np.ones((len(cameras), len(xyz)), bool)
    for i, (p, c) in enumerate(zip(xyz, colours, strict=True)):
        track = pycolmap.Track([pycolmap.TrackElement(k, i) for k in range(1, len(cameras) + 1) if seen[k - 1, i]])
        rec.add_point3D(np.asarray(p, np.float64), track, np.asarray(c, np.uint8))
    rec.update_point_3d_errors()  # ~1e-13 px: the observations are exact projections
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        rec.write_text(str(tmp))
        if folder.exists():
            shutil.rmtree(folder)
        tmp.rename(folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def city_model(city: SyntheticCity) -> CityModel:
    """The truth buildings as a :class:`CityModel`: LoD1 (volume-equivalent prism) and
    LoD2.2 (the exact solid) per building, in the city's local frame."""
    frame = city.frame
    buildings = []
    for b in city.buildings:
        fp = clean_footprint(b.footprint, 1e-6)
        solids = {"1": lod1_solid(fp, b.ground_z, b.lod1_z, frame), "2.2": b.solid}
        attrs = {"plan": b.plan, "roof_type": b.roof_type, "eave_z": b.eave_z, "ridge_z": b.ridge_z}
        buildings.append(Building(b.id, fp, b.ground_z, b.lod1_z, solids, attributes=attrs))
    meta = {"source": "recon3d.synthetic", "seed": city.seed}
    return CityModel(buildings, parse_crs(city.crs), frame, meta)


def views(city: SyntheticCity, cameras, surface: np.ndarray, transform) -> np.ndarray:
    """(rows, cols) float32: how many cameras have each cell's top surface point in frame.

    Parameters
    ----------
    surface : (rows, cols) float
        World heights of the top surface (the truth DSM); NaN cells see nothing.
    transform : affine.Affine
        Its world grid.
    """
    count = np.zeros(surface.shape, np.float32)
    for rows in row_blocks(surface.shape):
        x, y = cell_centres(transform, surface.shape, rows)
        z = surface[rows]
        local = np.column_stack([x.ravel(), y.ravel(), np.nan_to_num(z.ravel())]) - np.asarray(city.origin)
        seen = count[rows].reshape(-1)  # a view: the block's counts in place
        for cam in cameras:
            uv, depth = cam.project(local)
            seen += (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height)
        seen[~np.isfinite(z.ravel())] = 0
    return count


def _write_truth(folder: Path, city: SyntheticCity, cell: float, cameras) -> None:
    """dsm.tif, dtm.tif, views.tif, footprints.geojson, buildings.city.json, checkpoints.csv, trees.csv."""
    from recon3d.io.cityjson import write_cityjson
    from recon3d.io.geotiff import write_raster
    from recon3d.io.vectors import write_features

    crs = parse_crs(city.crs)
    transform, shape = grid_for_bounds(*city.bounds(), cell)
    tags = {"source": "recon3d.synthetic truth", "seed": str(city.seed)}
    tags["height"] = "metres above the synthetic datum (world = model + offset)"
    dsm = truth_dsm(city, transform, shape)
    dtm = truth_dtm(city, transform, shape)
    write_raster(Raster(dsm, transform, crs, {**tags, "product": "DSM"}), folder / "dsm.tif")
    write_raster(Raster(dtm, transform, crs, {**tags, "product": "DTM"}), folder / "dtm.tif")
    seen = views(city, cameras, dsm, transform)
    write_raster(Raster(seen, transform, crs, {**tags, "product": "images seeing the cell"}), folder / "views.tif")
    props = [
        {
            "id": b.id,
            "plan": b.plan,
            "roof_type": b.roof_type,
            "ground_z": round(b.ground_z, 4),
            "eave_z": round(b.eave_z, 4),
            "ridge_z": round(b.ridge_z, 4),
            "lod1_z": round(b.lod1_z, 4),
            "height": round(b.height, 4),
        }
        for b in city.buildings
    ]
    write_features(folder / "footprints.geojson", [b.footprint for b in city.buildings], props, crs)
    title = f"recon3d synthetic city, seed {city.seed} (truth)"
    meta = {"title": title, "referenceDate": _REFERENCE_DATE}
    write_cityjson(city_model(city), folder / "buildings.city.json", metadata=meta)
    _write_dem(folder / "coarse_dem.tif", city, crs, tags)
    spots, _, _ = checkpoints(city, spacing=50.0)
    rows = ["x,y,z"] + [f"{p[0]:.4f},{p[1]:.4f},{p[2]:.4f}" for p in spots[: len(spots) - len(city.buildings)]]
    _write_text(folder / "spot_heights.csv", "\n".join(rows) + "\n")
    xyz, ids, kinds = checkpoints(city)
    rows = ["x,y,z,id,kind"] + [
        f"{p[0]:.4f},{p[1]:.4f},{p[2]:.4f},{i},{k}"
        for p, i, k in zip(xyz, ids, kinds, strict=True)
    ]
    _write_text(folder / "checkpoints.csv", "\n".join(rows) + "\n")
    ox, oy, _ = city.origin
    rows = ["x,y,ground_z,top_z,crown_radius,crown,id"] + [
        f"{t.x + ox:.4f},{t.y + oy:.4f},{t.ground_z:.4f},{t.top_z:.4f},"
        f"{t.crown_radius:.4f},{t.crown},{t.id}"
        for t in city.trees
    ]
    _write_text(folder / "trees.csv", "\n".join(rows) + "\n")


def _write_dem(path: Path, city: SyntheticCity, crs, tags: dict) -> None:
    """The terrain on 20 m cells over the city and its margin, with 0.5 m of Gaussian noise."""
    from recon3d.io.geotiff import write_raster

    margin = min(-city.terrain.x0, 200.0)
    west, south, east, north = city.bounds()
    transform, shape = grid_for_bounds(west - margin, south - margin, east + margin, north + margin, 20.0)
    rng = np.random.default_rng(np.random.SeedSequence([int(city.seed), 50]))
    dem = truth_dtm(city, transform, shape) + rng.normal(0.0, 0.5, shape).astype(np.float32)
    write_raster(Raster(dem, transform, crs, {**tags, "product": "coarse DEM (20 m, 0.5 m noise)"}), path)


def _scene_record(city, cameras, gsd, cell, lighting, n_sparse) -> dict:
    """JSON-ready description of the scene (parameters, cameras in world coordinates)."""
    return {
        "generator": "recon3d.synthetic",
        "seed": city.seed,
        "size": city.size,
        "crs": city.crs,
        "offset": list(city.origin),
        "gsd": gsd,
        "cell_size": cell,
        "city": city.params,
        "n_buildings": len(city.buildings),
        "n_trees": len(city.trees),
        "n_sparse_points": n_sparse,
        "sun": {"azimuth": lighting.azimuth, "elevation": lighting.elevation},
        "pixel_samples": lighting.pixel_samples,
        "cameras": [
            {
                "name": c.name,
                "width": c.width,
                "height": c.height,
                "pinhole": [round(v, 9) for v in c.params],
                "center_world": [round(float(v), 6) for v in c.center + np.asarray(city.origin)],
            }
            for c in cameras
        ],
    }


def _write_png(path: Path, rgb: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(f"{path}: OpenCV could not write the image")


def _write_json(path: Path, doc: dict) -> None:
    _write_text(path, json.dumps(doc, indent=2) + "\n")


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
