"""Run the CARS satellite stereo pipeline (CNES) on one image pair: a peer for recon3d.

Peer comparison of recon3d's satellite path with CARS on the same pair. The script
writes a CARS configuration for two sensor images whose geomodels are RPCs (an OSSIM
``.geom`` beside the image if there is one, else the GeoTIFF RPC tags, read by CARS /
shareloc itself), runs the ``cars`` executable in a subprocess (CARS lives in its own
venv), and prints the DSM path and the wall time. With ``--truth`` it also scores the
DSM against a truth DSM: median, NMAD and share within 1 m of CARS - truth on the
truth grid.

Heights: the RPCs of the pair map ellipsoidal heights, and ``output.geoid`` is set to
``false`` so the DSM is in ellipsoidal heights too (CARS's default, ``true``, would
give EGM96 heights). ``--geoid-output`` restores the CARS default. A ``--dem`` is read
as ellipsoidal too (``initial_elevation.geoid: null``) unless ``--dem-geoid``.

Two departures from the CARS defaults, both needed on small (~900 px) crops, see
``cars_config``: 8 GB of RAM per worker, and pixels whose disparity range runs off the
epipolar image are kept (``--filter-incomplete`` restores CARS's default).

Only the standard library is needed to run CARS; ``--truth`` and a projected ``--dem``
(reprojected to EPSG:4326 for CARS) need numpy, scipy and rasterio.

Example::

    python scripts/peer_cars.py img1.tif img2.tif -o /tmp/cars_work/run \\
        --cars /work/peers/.venv-cars/bin/cars --truth truth/dsm.tif
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path


def geomodel_of(image: Path) -> str:
    """Return the geomodel CARS should read for ``image``.

    Parameters
    ----------
    image : Path
        Sensor image (GeoTIFF).

    Returns
    -------
    str
        The OSSIM ``.geom`` beside the image if it exists, else the image itself
        (CARS then reads the RPC tags of the GeoTIFF).
    """
    geom = image.with_suffix(".geom")
    return str(geom if geom.exists() else image)


def geographic_dem(dem: Path, out_dir: Path) -> Path:
    """Return ``dem`` in EPSG:4326, reprojecting a projected DEM into ``out_dir``.

    CARS 1.3 (shareloc) accepts a UTM DEM but then builds NaN epipolar grids
    ("RHS must contain only finite numbers"); in EPSG:4326 it runs. Cells left
    empty by the reprojection take the nearest valid height.

    Parameters
    ----------
    dem : Path
        Initial elevation GeoTIFF, any CRS.
    out_dir : Path
        Where the reprojected copy goes.

    Returns
    -------
    Path
        ``dem`` itself if already geographic, else the EPSG:4326 copy.
    """
    import numpy as np
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject
    from scipy.ndimage import distance_transform_edt

    with rasterio.open(dem) as src:
        if src.crs is not None and src.crs.is_geographic:
            return dem
        transform, width, height = calculate_default_transform(
            src.crs, "EPSG:4326", src.width, src.height, *src.bounds)
        z = src.read(1, masked=True).filled(np.nan).astype(np.float32)
        out = np.full((height, width), np.nan, np.float32)
        reproject(z, out, src_transform=src.transform, src_crs=src.crs, src_nodata=np.nan,
                  dst_transform=transform, dst_crs="EPSG:4326", dst_nodata=np.nan,
                  resampling=Resampling.bilinear)
    empty = np.isnan(out)
    if empty.all():
        raise ValueError(f"{dem}: no valid height")
    idx = distance_transform_edt(empty, return_distances=False, return_indices=True)
    out = out[tuple(idx)]
    path = out_dir / "initial_elevation_4326.tif"
    with rasterio.open(path, "w", driver="GTiff", width=width, height=height, count=1,
                       dtype="float32", crs="EPSG:4326", transform=transform) as dst:
        dst.write(out, 1)
    return path


def cars_config(img1: Path, img2: Path, out_dir: Path, dem: Path | None = None,
                resolution: float | None = None, geoid_output: bool = False,
                dem_geoid: bool = False, workers: int = 2, ram_mb: int = 8000,
                keep_incomplete: bool = True) -> dict:
    """Build a CARS (1.x) configuration for one pair.

    Parameters
    ----------
    img1, img2 : Path
        Left and right sensor images.
    out_dir : Path
        CARS output directory.
    dem : Path, optional
        Initial elevation; without it CARS starts from a constant height and refines
        it with its own multi-resolution passes.
    resolution : float, optional
        DSM cell size in metres (CARS default 0.5 m x the image subsampling).
    geoid_output : bool
        Heights above the EGM96 geoid (CARS default) instead of the ellipsoid.
    dem_geoid : bool
        The DEM is above the EGM96 geoid (e.g. SRTM) instead of the ellipsoid.
    workers : int
        Number of multiprocessing workers.
    ram_mb : int
        RAM per worker (MB). CARS sizes its tiles from it and, when a tile's
        disparity range does not fit, crops the range (and flags those pixels
        "incomplete"); with the default 2000 MB the 1/4-resolution range of the
        synthetic mountain pair (~336 px) was cropped.
    keep_incomplete : bool
        Set ``dense_matching.filter_incomplete_disparity_range`` to false. CARS
        widens the sparse disparity bounds by 500 m below / 1000 m above; on a crop
        of ~900 px that range runs off the epipolar image for every pixel, pandora
        flags them all "incomplete range" and CARS drops them (empty DSM at 1/4).

    Returns
    -------
    dict
        The configuration, ready for ``json.dump``.
    """
    sensors = {name: {"image": str(img.resolve()), "geomodel": geomodel_of(img.resolve())}
               for name, img in (("one", img1), ("two", img2))}
    inputs = {"sensors": sensors, "pairing": [["one", "two"]]}
    if dem is not None:
        elevation = {"dem": str(dem.resolve())}
        if not dem_geoid:
            elevation["geoid"] = None  # JSON null: DEM is ellipsoidal
        inputs["initial_elevation"] = elevation
    output = {"directory": str(out_dir.resolve()), "geoid": geoid_output}
    if resolution is not None:
        output["resolution"] = resolution
    conf = {"input": inputs, "output": output,
            "orchestrator": {"mode": "multiprocessing", "nb_workers": workers,
                             "max_ram_per_worker": ram_mb}}
    if keep_incomplete:
        conf["surface_modeling"] = {"applications": {"all": {"dense_matching": {
            "filter_incomplete_disparity_range": False}}}}
    return conf


def find_dsm(out_dir: Path) -> Path:
    """Return CARS's DSM in ``out_dir`` (``dsm/dsm.tif``, else the first ``dsm*.tif``)."""
    main = out_dir / "dsm" / "dsm.tif"
    if main.exists():
        return main
    found = sorted(out_dir.rglob("dsm*.tif"), key=lambda p: len(p.parts))
    if not found:
        raise FileNotFoundError(f"no DSM under {out_dir}")
    return found[0]


def compare(dsm_path: Path, truth_path: Path) -> dict:
    """Score a DSM against a truth DSM on the truth grid.

    Parameters
    ----------
    dsm_path : Path
        DSM to score (any CRS; bilinear resampling onto the truth grid).
    truth_path : Path
        Truth DSM, same height reference.

    Returns
    -------
    dict
        ``crs``, ``res``, ``finite`` (share of finite cells of the DSM on its own grid),
        ``overlap`` (share of truth cells where both are finite), ``median``, ``nmad``
        and ``within_1m`` (share, of those cells) of DSM - truth.
    """
    import numpy as np
    import rasterio
    from rasterio.warp import Resampling, reproject

    with rasterio.open(dsm_path) as src:
        z = src.read(1, masked=True).filled(np.nan).astype(np.float64)
        crs, res, transform = src.crs, src.res, src.transform
    # e.g. "32636 + WGS84 ellipsoidal height"
    name = crs.to_wkt().split('"')[1] if crs is not None else None
    out = {"crs": name, "res": res, "finite": float(np.isfinite(z).mean())}
    if truth_path is None:
        return out
    with rasterio.open(truth_path) as ref:
        truth = ref.read(1, masked=True).filled(np.nan).astype(np.float64)
        on_truth = np.full(truth.shape, np.nan)
        reproject(z, on_truth, src_transform=transform, src_crs=crs, src_nodata=np.nan,
                  dst_transform=ref.transform, dst_crs=ref.crs, dst_nodata=np.nan,
                  resampling=Resampling.bilinear)
    e = (on_truth - truth)[np.isfinite(on_truth) & np.isfinite(truth)]
    out["overlap"] = e.size / truth.size
    if e.size:
        med = float(np.median(e))
        out.update(median=med, nmad=float(1.4826 * np.median(np.abs(e - med))),
                   within_1m=float((np.abs(e) <= 1.0).mean()))
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("img1", type=Path)
    ap.add_argument("img2", type=Path)
    ap.add_argument("-o", "--out", type=Path, required=True, help="CARS output directory")
    ap.add_argument("--cars", default=None, help="cars executable (default: cars on PATH)")
    ap.add_argument("--dem", type=Path, default=None, help="initial elevation GeoTIFF")
    ap.add_argument("--dem-geoid", action="store_true", help="the DEM is above EGM96")
    ap.add_argument("--resolution", type=float, default=None, help="DSM cell size (m)")
    ap.add_argument("--geoid-output", action="store_true", help="DSM above EGM96")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--ram-mb", type=int, default=8000, help="RAM per CARS worker (MB)")
    ap.add_argument("--filter-incomplete", action="store_true",
                    help="keep CARS's default dropping of pixels with an incomplete range")
    ap.add_argument("--truth", type=Path, default=None, help="truth DSM to score against")
    args = ap.parse_args(argv)

    cars = args.cars or shutil.which("cars")
    if cars is None:
        ap.error("no cars executable on PATH; give --cars")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.dem is not None:
        args.dem = geographic_dem(args.dem, args.out)
    conf = cars_config(args.img1, args.img2, args.out, args.dem, args.resolution,
                       args.geoid_output, args.dem_geoid, args.workers, args.ram_mb,
                       not args.filter_incomplete)
    conf_path = args.out / "cars_config.json"
    conf_path.write_text(json.dumps(conf, indent=2))

    # CARS's own venv must come first on PATH for its worker processes.
    env = dict(os.environ, PATH=f"{Path(cars).resolve().parent}{os.pathsep}"
               f"{os.environ.get('PATH', '')}")
    env.pop("PYTHONPATH", None)
    env.pop("VIRTUAL_ENV", None)
    t0 = time.perf_counter()
    run = subprocess.run([cars, "--logtype", "plain", str(conf_path)], env=env)
    wall = time.perf_counter() - t0
    print(f"cars exit code {run.returncode}, wall time {wall:.1f} s")
    if run.returncode != 0:
        return run.returncode
    dsm = find_dsm(args.out)
    print(f"DSM: {dsm.resolve()}")
    try:
        stats = compare(dsm, args.truth)
    except ImportError:
        if args.truth is not None:
            raise
        return 0
    print(json.dumps(dict(stats, wall_s=round(wall, 1), dsm=str(dsm.resolve())), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
