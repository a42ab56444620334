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
    truth/scene.json                     parameters of the scene (seed, gsd, cameras...)

Every file is a deterministic function of the parameters (same seed, same bytes).
"""

from __future__ import annotations

import json
import logging
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
    checkpoints,
    make_city,
    nice_cell_size,
    truth_dsm,
    truth_dtm,
)
from recon3d.synthetic.render import (
    Lighting,
    PinholeCamera,
    Render,
    check_coverage,
    render_pair,
    sparse_points,
    stereo_cameras,
)

log = logging.getLogger(__name__)

__all__ = ["SceneInfo", "city_model", "write_colmap", "write_scene"]

#: CityJSON ``referenceDate`` of the truth (fixed, so the file is byte-identical per seed).
_REFERENCE_DATE = "2024-01-01"


@dataclass
class SceneInfo:
    """What :func:`write_scene` wrote.

    Attributes
    ----------
    folder : Path
    city : SyntheticCity
    cameras : (PinholeCamera, PinholeCamera)
        In local (model) coordinates.
    renders : list of Render
        Images and the surface point seen through every pixel centre.
    sparse_xyz : (n, 3) float64
        Local coordinates of the COLMAP model's 3-D points.
    sparse_uv : (2, n, 2) float64
        Their observations in each image (COLMAP pixel convention).
    cell_size : float
        Cell size of the truth rasters.
    timings : dict of str to float
        Seconds per step ("city", "render", "truth", "write").
    """

    folder: Path
    city: SyntheticCity
    cameras: tuple[PinholeCamera, PinholeCamera]
    renders: list[Render]
    sparse_xyz: np.ndarray
    sparse_uv: np.ndarray
    cell_size: float
    timings: dict[str, float] = field(default_factory=dict)


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

    start = time.perf_counter()
    renders = render_pair(city, cameras, lighting=lighting, seed=seed)
    xyz, uv = sparse_points(city, cameras, n_sparse, seed=seed)
    timings["render"] = time.perf_counter() - start

    start = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    for r in renders:
        _write_png(folder / "images" / r.camera.name, r.image)
    rows = np.clip(uv[0, :, 1].astype(int), 0, height - 1)
    cols = np.clip(uv[0, :, 0].astype(int), 0, width - 1)
    colours = renders[0].image[rows, cols]
    write_colmap(folder / "sparse", cameras, xyz, uv, colours)
    _write_json(folder / "georef.json", {"crs": city.crs, "offset": list(city.origin)})
    timings["write"] = time.perf_counter() - start

    start = time.perf_counter()
    cell = nice_cell_size(gsd)
    _write_truth(folder / "truth", city, cell)
    record = _scene_record(city, cameras, gsd, cell, base_to_height, lighting, len(xyz))
    _write_json(folder / "truth" / "scene.json", record)
    timings["truth"] = time.perf_counter() - start
    log.info(
        "synthetic scene %s: %d buildings, %d trees, %d sparse points; %s",
        folder, len(city.buildings), len(city.trees), len(xyz),
        ", ".join(f"{k} {v:.2f} s" for k, v in timings.items()),
    )
    return SceneInfo(folder, city, cameras, renders, xyz, uv, cell, timings)


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
) -> None:
    """Write a COLMAP text model: one PINHOLE camera per image, posed images, 3-D points.

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
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    for k, cam in enumerate(cameras, start=1):
        camera = pycolmap.Camera(
            model="PINHOLE", width=cam.width, height=cam.height, params=cam.params, camera_id=k
        )
        rec.add_camera_with_trivial_rig(camera)
        keypoints = np.asarray(uv[k - 1], np.float64)
        image = pycolmap.Image(name=cam.name, keypoints=keypoints, camera_id=k, image_id=k)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t.reshape(3, 1))
        rec.add_image_with_trivial_frame(image, pose)
    if colours is None:
        colours = np.full((len(xyz), 3), 128, np.uint8)
    for i, (p, c) in enumerate(zip(xyz, colours, strict=True)):
        track = pycolmap.Track([pycolmap.TrackElement(k, i) for k in range(1, len(cameras) + 1)])
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


def _write_truth(folder: Path, city: SyntheticCity, cell: float) -> None:
    """dsm.tif, dtm.tif, footprints.geojson, buildings.city.json, checkpoints.csv, trees.csv."""
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


def _scene_record(city, cameras, gsd, cell, b_h, lighting, n_sparse) -> dict:
    """JSON-ready description of the scene (parameters, cameras in world coordinates)."""
    return {
        "generator": "recon3d.synthetic",
        "seed": city.seed,
        "size": city.size,
        "crs": city.crs,
        "offset": list(city.origin),
        "gsd": gsd,
        "cell_size": cell,
        "base_to_height": b_h,
        "n_buildings": len(city.buildings),
        "n_trees": len(city.trees),
        "n_sparse_points": n_sparse,
        "sun": {"azimuth": lighting.azimuth, "elevation": lighting.elevation},
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
