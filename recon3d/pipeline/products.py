"""Writing a run's products into its work folder, and run.json's record of the run."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from recon3d import __version__
from recon3d.core.geo import crs_name
from recon3d.core.pointcloud import PointCloud
from recon3d.core.raster import Raster
from recon3d.io import vectors
from recon3d.io.geotiff import write_raster
from recon3d.pipeline.output import Products as P

if TYPE_CHECKING:
    from recon3d.pipeline.run import Run

__all__ = ["run_record", "write_json", "write_products"]


def write_products(r: Run) -> None:
    """Every product of the run into ``r.work_dir`` (see DESIGN.md's output contract).

    The rasters and cloud.laz go on a second thread while this one writes the models and
    the vectors: GDAL and lazrs let go of the interpreter while they compress, the model
    writers are Python, so the two overlap on two cores (the 16 x Delft survey's write
    stage, two runs each: 3.7 s one after the other, 3.3-3.4 s side by side). Each
    file's bytes depend on its inputs alone, not on which thread finishes first.
    """
    for raster in (r.surface.dsm, r.terrain.dtm, r.terrain.ndsm, r.quality.model_dsm):
        raster.tags.setdefault("height_units", r.units.name)  # before the threads share the rasters
    with ThreadPoolExecutor(1) as pool:
        rasters = pool.submit(_write_rasters_and_cloud, r)
        _write_models(r)
        rasters.result()
    r.report["warnings"] = r.warnings
    write_json(r.work_dir / P.REPORT, r.report)


def _write_rasters_and_cloud(r: Run) -> None:
    w, q, sf, t = r.work_dir, r.quality, r.surface, r.terrain
    for name, raster in ((P.DSM, sf.dsm), (P.DTM, t.dtm), (P.NDSM, t.ndsm), (P.MODEL_DSM, q.model_dsm)):
        write_raster(raster, w / name)
    if q.ortho is not None:
        from recon3d.io.geotiff import write_image

        grid = Raster(np.zeros((1, 1)), q.ortho.transform, sf.dsm.crs,
                      {"product": f"true orthophoto on the {r.config.ortho.surface}"})
        write_image(q.ortho.data, grid, w / P.ORTHO, mask=q.ortho.seen)
        write_raster(q.ortho_diff, w / P.ORTHO_DIFF)
    write_cloud(r, w / P.CLOUD)


def _write_models(r: Run) -> None:
    from recon3d.io.cityjson import write_cityjson
    from recon3d.io.gltf import write_glb
    from recon3d.io.obj import write_obj
    from recon3d.io.tiles3d import write_3dtiles

    w, q, city = r.work_dir, r.quality, r.city
    write_cityjson(city, w / P.CITY)
    write_obj(city, w / P.OBJ)
    write_glb(city, w / P.GLB)
    if q.textured is not None:
        from recon3d.io.gltf import write_textured_glb

        write_textured_glb(city, q.textured, w / P.GLB_TEXTURED)
    write_3dtiles(city, w / P.TILES)
    write_footprints(r, w / P.FOOTPRINTS, w / P.FOOTPRINTS_GPKG)
    if q.changes is not None:
        from recon3d.quality import change

        geoms, props = change.change_features(q.changes)
        vectors.write_features(w / P.CHANGES, geoms, props, city.crs)
        write_raster(change.change_raster(q.changes, r.surface.dsm), w / P.CHANGES_RASTER)
        write_cityjson(change.updated_model(r.source.old_buildings, city, q.changes), w / P.UPDATED_CITY)


def write_cloud(r: Run, path: Path) -> None:
    """cloud.laz: every point once with recon3d's classes (ground 2, vegetation 5, building
    6, other 1, noise 7: stereo points guessed over hidden ground), the tiles' records
    one after the other in their Morton order, so that a survey gives the same file
    whatever its tiling and however it was delivered (dated like the city model)."""
    from recon3d.io.las import LasStreamWriter

    s = r.source.summary
    with np.load(r.passes["finish"][0]) as data:
        names = [k[2:] for k in data.files if k.startswith("a_")]
    with LasStreamWriter(path, s.crs, names, s.bounds[0], r.city.metadata["referenceDate"]) as writer:
        for tile_path in r.passes["finish"]:
            with np.load(tile_path) as data:
                writer.write(PointCloud(data["xyz"], {k: data[f"a_{k}"] for k in names}))


def write_footprints(r: Run, *paths: Path) -> None:
    """The footprints with their building's status and heights, to each of ``paths``
    (GeoJSON, and a GeoPackage whose CRS GIS software reads whatever it is)."""
    u, city = r.units, r.city
    props = []
    for b in city:
        lods = sorted(b.solids, key=float)
        p = {"id": b.id, "status": b.status, "reason": b.reason or "", "lod": lods[-1] if lods else "",
             "roof_type": b.attributes.get("roof_type", "") if b.solids else ""}
        p.update(ground_z=_num(b.ground_z), roof_z=_num(b.roof_z), height_m=_num(b.height * u.vertical))
        p.update({k: v for k, v in b.attributes.items() if isinstance(v, str | int | float) and k not in p})
        props.append(p)
    for path in paths:
        vectors.write_features(path, [b.footprint for b in city], props, city.crs,
                               date=city.metadata.get("referenceDate"))


def _num(v: float) -> float | None:
    return round(float(v), 3) if np.isfinite(v) else None


def run_record(r: Run) -> dict:
    """run.json: inputs, the resolved configuration, every automatic choice and why,
    notes, warnings, versions and timings."""
    from importlib.metadata import PackageNotFoundError, version

    def installed(name: str) -> str:  # the installed release, without importing it
        try:
            return version(name)
        except PackageNotFoundError:
            return "?"

    i, s = r.inputs, r.source
    kind = r.inputs.kind
    return {
        "recon3d": __version__,
        "inputs": {
            "input": str(i.input_path),
            "kind": {"satellite": "satellite pair", "frame": "stereo scene"}.get(kind)
            or (f"point cloud in {len(i.tile_paths)} tiles" if i.tile_paths else "point cloud"),
            "tiles": [str(p) for p in i.tile_paths] if i.tile_paths else None,
            "second_image": str(i.satellite_paths[1]) if i.satellite_paths else None,
            "points": s.summary.count,
            "crs": crs_name(s.crs),
            "crs_identification": s.crs_identification.record() if s.crs_identification else None,
            "units": {"horizontal": r.units.name, "metres_per_unit": r.units.horizontal,
                      "vertical_metres_per_unit": r.units.vertical, "vertical_from": r.units.vertical_source},
            "provider_classes": s.summary.provider_classes,
            "footprints": str(i.footprints) if i.footprints else None,
            "checkpoints": str(i.checkpoints) if i.checkpoints else None,
            "breaklines": str(i.breaklines) if i.breaklines else None,
            "altimetry": str(i.altimetry) if i.altimetry else None,
            "dem": str(i.dem) if i.dem else None,
            "old_buildings": str(i.old_buildings) if i.old_buildings else None,
            "gcps": str(i.gcps) if i.gcps else None,
        },
        "config": r.config.to_dict(),
        "chosen": r.auto,
        "local_frame_origin": list(r.city.frame.origin),
        "notes": r.notes,
        "warnings": r.warnings,
        "versions": {name: installed(name) for name in ("numpy", "scipy", "laspy", "rasterio", "shapely", "trimesh")},
        "timings_s": r.timings,
    }


def write_json(path: Path, data: dict) -> None:
    """``data`` as indented UTF-8 JSON, written atomically."""
    from recon3d.io import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, ensure_ascii=False, default=_json_default), encoding="utf-8")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")
