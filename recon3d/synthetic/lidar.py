"""Airborne LiDAR of a procedural city: points, their true classes, a LAS file.

Rays fall from above at random positions (a given density per square metre,
slightly off nadir like the edge of a swath), and each returns from the first surface
it hits; in a tree crown, the first leaf it meets, some way inside the crown's hull.
A share of the rays that hit foliage goes on through the crown and returns
again below it, as the later returns of a real pulse do, so ground under trees is
sampled. Heights get Gaussian noise. Each point's class is the truth of the surface
it hit: ground (2), building (6: roofs and walls), vegetation (5: foliage and bark),
in the ASPRS codes the readers expect.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon3d.synthetic.city import BARK, FOLIAGE, GROUND, SyntheticCity

__all__ = ["LidarScan", "scan_city", "write_scan"]


@dataclass
class LidarScan:
    """A synthetic scan in world coordinates.

    Attributes
    ----------
    xyz : (n, 3) float64
        World coordinates (the city's CRS).
    classification : (n,) uint8
        True ASPRS class of the surface each point lies on (2, 5 or 6).
    return_number, number_of_returns : (n,) uint8
    crs : str
    """

    xyz: np.ndarray
    classification: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    crs: str


def scan_city(
    city: SyntheticCity,
    density: float,
    *,
    seed: int = 0,
    noise: float = 0.03,
    penetration: float = 0.4,
    max_angle: float = 10.0,
    crown_depth: float = 0.6,
    area: tuple[float, float, float, float] | None = None,
) -> LidarScan:
    """Scan ``city`` with rays from above.

    Parameters
    ----------
    city : SyntheticCity
    density : float
        First returns per square metre.
    seed : int
    noise : float
        Standard deviation (m) of the height noise.
    penetration : float
        Share of the rays hitting foliage that return a second time, below the crown.
    max_angle : float
        Largest angle (degrees) of a ray from the vertical, drawn uniformly.
    crown_depth : float
        Mean depth (m) below a crown's hull at which a leaf returns the pulse
        (exponential, at most three times the mean): crowns are rough volumes.
    area : (xmin, ymin, xmax, ymax), optional
        Local extent scanned (default the city, ``[0, size]^2``).

    Returns
    -------
    LidarScan
    """
    from recon3d.core.o3d import open3d

    o3d = open3d()
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = area or (0.0, 0.0, city.size, city.size)
    n = max(1, int(round(density * (x1 - x0) * (y1 - y0))))
    top = float(city.vertices[:, 2].max()) + 50.0
    tilt = np.radians(rng.uniform(0.0, max_angle, n))
    azimuth = rng.uniform(0.0, 2 * np.pi, n)
    direction = np.column_stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), -np.cos(tilt)])
    # rays aimed at the sampled ground position: start above it, back along the ray
    target = np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), np.zeros(n)])
    origin = target - direction * (top / np.cos(tilt))[:, None]
    scene = city.raycaster()

    def cast(o, d):
        hit = scene.cast_rays(o3d.core.Tensor(np.hstack([o, d]).astype(np.float32)))
        return hit["t_hit"].numpy().astype(np.float64), hit["primitive_ids"].numpy().astype(np.int64)

    t, prim = cast(origin, direction)
    ok = np.isfinite(t)
    material = city.face_material[prim[ok]]
    # leaves return from inside the crown, not from its hull: a depth into it
    depth = np.where(material == FOLIAGE, np.minimum(rng.exponential(crown_depth, ok.sum()), 3 * crown_depth), 0.0)
    down = direction[ok]
    first = origin[ok] + down * (t[ok] + depth)[:, None]
    # later returns through the crown: a fresh ray from just below the first hit
    crown = np.isin(material, (FOLIAGE, BARK)) & (rng.uniform(size=len(first)) < penetration)
    start = first[crown] + down[crown] * 0.5
    t2, prim2 = cast(start, down[crown])
    ok2 = np.isfinite(t2)
    second = start[ok2] + down[crown][ok2] * t2[ok2, None]
    xyz = np.vstack([first, second])
    mat = np.concatenate([material, city.face_material[prim2[ok2]]])
    classes = np.where(mat == GROUND, 2, np.where(np.isin(mat, (FOLIAGE, BARK)), 5, 6)).astype(np.uint8)
    returns = np.ones(len(xyz), np.uint8)
    count = np.ones(len(xyz), np.uint8)
    two = np.flatnonzero(crown)[ok2]
    count[two] = 2
    returns[len(first):] = 2
    count[len(first):] = 2
    xyz[:, 2] += rng.normal(0.0, noise, len(xyz))
    order = np.lexsort((xyz[:, 1], xyz[:, 0]))  # a stable order, not the rays'
    return LidarScan(xyz[order] + np.asarray(city.origin), classes[order], returns[order], count[order], city.crs)


def write_scan(scan: LidarScan, path: str | Path, *, classes: bool = True, with_crs: bool = True) -> Path:
    """Write ``scan`` as LAS 1.4 (point format 6, centimetre scale); ``classes=False``
    leaves every point unclassified (1), ``with_crs=False`` writes no CRS."""
    import laspy
    import pyproj

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = [0.01, 0.01, 0.01]
    header.offsets = np.floor(scan.xyz.min(axis=0))
    if with_crs:
        header.add_crs(pyproj.CRS.from_user_input(scan.crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = scan.xyz.T
    las.classification = scan.classification if classes else np.ones(len(scan.xyz), np.uint8)
    las.return_number = scan.return_number
    las.number_of_returns = scan.number_of_returns
    path = Path(path)
    las.write(path)
    return path


#: Projected CRSs of the random surveys, each with an origin inside its area of use.
SURVEY_CRSS = {
    "EPSG:32631": (500000.0, 5400000.0),  # UTM 31N
    "EPSG:2154": (650000.0, 6860000.0),  # Lambert-93
    "EPSG:28992": (85000.0, 446000.0),  # RD New
    "EPSG:3067": (385000.0, 6672000.0),  # ETRS-TM35FIN
}


def random_survey(seed: int) -> dict:
    """A LiDAR survey drawn over the ranges users bring, deterministic for ``seed``.

    Returns
    -------
    dict
        ``make_city`` arguments (``city``; with trees, two surveys in five also get
        groves of touching crowns), scan arguments (``scan``: density 1-25
        points per m2, noise 1-8 cm, crown penetration 0-0.6, off-nadir angle 0-20
        degrees) and the file (``file``: LAS or LAZ, with or without classes and CRS,
        terrain height offset 0-2500 m).
    """
    from recon3d.synthetic.city import LAYOUTS, TERRAINS, TREES

    rng = np.random.default_rng([seed, 17])
    crs = str(rng.choice(sorted(SURVEY_CRSS)))
    x, y = SURVEY_CRSS[crs]
    spec = {
        "seed": seed,
        "city": {
            "seed": int(rng.integers(0, 2**31)),
            "size": float(rng.choice([60.0, 80.0, 120.0])),
            "terrain": str(rng.choice([t for t in TERRAINS if t != "mountain"])),
            "layout": str(rng.choice([k for k in LAYOUTS if k != "none"])),
            "trees": str(rng.choice(TREES)),
            "crs": crs,
            "origin": (x, y, float(rng.choice([0.0, 40.0, 350.0, 2500.0]))),
        },
        "scan": {
            "density": float(np.round(np.exp(rng.uniform(np.log(1.0), np.log(25.0))), 1)),
            "noise": float(np.round(rng.uniform(0.01, 0.08), 3)),
            "penetration": float(np.round(rng.uniform(0.0, 0.6), 2)),
            "max_angle": float(np.round(rng.uniform(0.0, 20.0), 1)),
        },
        "file": {
            "suffix": str(rng.choice([".las", ".laz"])),
            "classes": bool(rng.uniform() < 0.6),
            "with_crs": bool(rng.uniform() < 0.8),
        },
    }
    # drawn last, so the surveys of the earlier family keep every other value
    if rng.uniform() < 0.4 and spec["city"]["trees"] != "none":
        spec["city"]["groves"] = True
    return spec


def write_survey(folder: str | Path, spec: dict) -> tuple[Path, SyntheticCity]:
    """Make the city and the scan of a :func:`random_survey` and write the point file
    into ``folder`` (created). Returns the file and the city (its truth)."""
    from recon3d.synthetic.city import make_city

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    city = make_city(**spec["city"])
    scan = scan_city(city, seed=spec["seed"], **spec["scan"])
    f = spec["file"]
    path = write_scan(scan, folder / f"survey_{spec['seed']}{f['suffix']}", classes=f["classes"], with_crs=f["with_crs"])
    return path, city
