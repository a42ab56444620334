"""Accuracy of the products against reference heights and reference classes."""

from __future__ import annotations

import numpy as np

from recon3d.core.accuracy import AccuracyReport
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster
from recon3d.io.checkpoints import CheckPoints

__all__ = [
    "against_checkpoints",
    "against_points",
    "against_raster",
    "building_coverage",
    "coverage_counts",
    "coverage_scores",
    "evaluate_ground",
    "filter_counts",
    "filter_scores",
    "ground_filter_errors",
    "landmark_height",
    "model_check_cells",
    "roof_errors",
]


def against_points(
    raster: Raster, xyz: np.ndarray, *, product: str, reference: str, units: Units
) -> AccuracyReport:
    """Raster (bilinear) minus reference heights at (n, 3) reference points, in metres."""
    errors = raster.sample(xyz[:, 0], xyz[:, 1]) - xyz[:, 2]
    return AccuracyReport.from_errors(
        errors, product=product, reference=reference, metres_per_unit=units.vertical
    )


def against_checkpoints(
    products: dict[str, Raster], points: CheckPoints, units: Units
) -> list[AccuracyReport]:
    """Tables for every product against the check points that measure it.

    The DSM and the model DSM are compared with every check point, the DTM with the
    ground points; with kinds given, the DSM and the model DSM also get a roof-only table.
    """
    tables = []
    subsets = {"all": np.ones(len(points), bool)}
    for kind in ("ground", "roof"):
        if np.any(points.kinds == kind):
            subsets[kind] = points.kinds == kind
    for name, raster in products.items():
        for kind, sel in subsets.items():
            if name == "DTM" and kind != "ground":
                continue
            tables.append(
                against_points(
                    raster, points.xyz[sel], product=name, reference=f"check points ({kind})", units=units
                )
            )
    return tables


def ground_filter_errors(is_ground: np.ndarray, reference_classes: np.ndarray) -> dict:
    """ISPRS filter-test errors against the provider's classes.

    Points the provider labelled ground (2) against vegetation or building (3, 4, 5, 6);
    unclassified and other classes are left out. Type I: ground rejected; Type II:
    object accepted as ground; total: all misclassified; Cohen's kappa.
    """
    return filter_scores(filter_counts(is_ground, reference_classes))


def filter_counts(is_ground: np.ndarray, reference_classes: np.ndarray) -> np.ndarray:
    """(5,) int64 counts of :func:`ground_filter_errors` (summed over tiles): provider
    ground kept and rejected, objects accepted and rejected, and all points."""
    ref_ground = reference_classes == ASPRS.GROUND
    ref_object = np.isin(reference_classes, (3, 4, 5, 6))
    return np.array([np.sum(ref_ground & is_ground), np.sum(ref_ground & ~is_ground), np.sum(ref_object & is_ground),
                     np.sum(ref_object & ~is_ground), len(reference_classes)], np.int64)


def filter_scores(counts: np.ndarray) -> dict:
    """:func:`ground_filter_errors`'s figures from :func:`filter_counts`."""
    a, b, c, d, points = (int(v) for v in counts)
    n = a + b + c + d
    if n == 0:
        return {"n": 0}
    po = (a + d) / n
    pe = ((a + b) * (a + c) + (c + d) * (b + d)) / n**2
    return {
        "n": n,
        "type_i_percent": 100.0 * b / max(a + b, 1),
        "type_ii_percent": 100.0 * c / max(c + d, 1),
        "total_percent": 100.0 * (b + c) / n,
        "kappa": (po - pe) / (1 - pe) if pe < 1 else 1.0,
        "scored_share_percent": 100.0 * (n / points),
        # without objects (a provider classifying ground only) Type II and kappa do not apply
        "reference_ground": a + b,
        "reference_objects": c + d,
    }


def building_coverage(cloud: PointCloud, reference_classes: np.ndarray, labels: np.ndarray, grid: Raster) -> dict:
    """Point-based detection scores against the provider's building class (6).

    completeness: share of provider building points inside a footprint;
    correctness: share of points inside footprints, and not ground, that the
    provider calls building.
    """
    return coverage_scores(coverage_counts(cloud, reference_classes, labels, grid))


def coverage_counts(cloud: PointCloud, reference_classes: np.ndarray, labels: np.ndarray, grid: Raster) -> np.ndarray:
    """(4,) int64 counts of :func:`building_coverage` (summed over tiles): provider building
    points, those inside a footprint, points inside a footprint and not ground, those the
    provider calls building."""
    row, col = grid.rowcol(cloud.xyz[:, 0], cloud.xyz[:, 1])
    ok = (row >= 0) & (row < grid.shape[0]) & (col >= 0) & (col < grid.shape[1])
    inside = np.zeros(len(cloud), bool)
    inside[ok] = labels[row[ok], col[ok]] > 0
    ref_building = reference_classes == ASPRS.BUILDING
    above = inside & (reference_classes != ASPRS.GROUND)
    return np.array([ref_building.sum(), (inside & ref_building).sum(), above.sum(), (above & ref_building).sum()],
                    np.int64)


def coverage_scores(counts: np.ndarray) -> dict:
    """:func:`building_coverage`'s figures from :func:`coverage_counts`."""
    ref, found, above, right = (int(v) for v in counts)
    return {
        "reference_building_points": ref,
        "completeness_percent": 100.0 * (found / ref) if ref else None,
        "correctness_percent": 100.0 * (right / above) if above else None,
    }


def evaluate_ground(
    classified: PointCloud,
    reference: PointCloud,
    units: Units,
    *,
    dtm: Raster | None = None,
    checkpoints: CheckPoints | None = None,
) -> dict:
    """Ground filter and DTM of a run against a provider-classified reference cloud.

    Parameters
    ----------
    classified : PointCloud
        recon3d's output cloud (class 2 = ground).
    reference : PointCloud
        The same points classified by the provider.
    units : Units
    dtm : Raster, optional
        recon3d's DTM; compared with a DTM interpolated the same way from the
        provider's ground points, over the cells that hold reference points.
    checkpoints : CheckPoints, optional
        Compared with the DTM (ground and unlabelled points).

    Returns
    -------
    dict
        ``{"points": ground_filter_errors(...), "accuracy": [AccuracyReport dicts]}``.

    Raises
    ------
    InputError
        When the two clouds are not the same points.
    """
    from recon3d.errors import InputError
    from recon3d.terrain.dsm import grid_points
    from recon3d.terrain.dtm import make_dtm

    if reference.classification is None:
        raise InputError("the reference cloud carries no classification")
    order = _match_points(classified.xyz, reference.xyz, tolerance=units.length(0.01))
    if order is None:
        raise InputError("the classified and reference clouds are not the same points")
    is_ground = classified.classification[order] == ASPRS.GROUND
    out = {"points": ground_filter_errors(is_ground, reference.classification), "accuracy": []}
    if dtm is not None:
        ref_ground = reference.xyz[reference.classification == ASPRS.GROUND]
        ref_dtm = make_dtm(ref_ground, dtm)
        covered = grid_points(reference.xyz, dtm.transform, dtm.shape, reducer="count") > 0
        out["accuracy"].append(
            AccuracyReport.from_errors(
                (dtm.data - ref_dtm.data)[covered],
                product="DTM",
                reference="DTM from provider ground points",
                metres_per_unit=units.vertical,
            ).to_dict()
        )
        out["accuracy"].append(
            against_points(dtm, ref_ground, product="DTM", reference="provider ground points", units=units).to_dict()
        )
    if checkpoints is not None and dtm is not None:
        sel = checkpoints.kinds != "roof"
        out["accuracy"].append(
            against_points(dtm, checkpoints.xyz[sel], product="DTM", reference="check points", units=units).to_dict()
        )
    return out


def _match_points(a: np.ndarray, b: np.ndarray, *, tolerance: float) -> np.ndarray | None:
    """Index into ``a`` of the point matching each point of ``b``, or None if some have no match."""
    if len(a) == len(b) and np.abs(a - b).max() <= tolerance:
        return np.arange(len(b))
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(a).query(b, distance_upper_bound=tolerance)
    return idx if np.isfinite(dist).all() else None


def against_raster(product: Raster, reference: Raster, *, product_name: str, reference_name: str, units: Units) -> AccuracyReport:
    """Product minus reference, cell by cell on the product's grid.

    The reference is resampled onto the product grid with the highest value per
    product cell (``rasterio.warp.reproject``, ``Resampling.max``), the definition of a
    DSM cell; point-sampling a finer reference would charge every building edge with a
    wall's height. Cells where either is NaN are left out; ``n`` counts the compared cells.
    """
    ref = resample_max(reference, product)
    return AccuracyReport.from_errors(
        (product.data - ref).ravel(), product=product_name, reference=reference_name, metres_per_unit=units.vertical
    )


def resample_max(source: Raster, grid: Raster) -> np.ndarray:
    """(rows, cols) float32: ``source`` on the grid of ``grid``, highest value per cell, NaN outside."""
    from rasterio.warp import Resampling, reproject

    from recon3d.core.geo import to_rasterio_crs

    out = np.full(grid.shape, np.nan, np.float32)
    crs = to_rasterio_crs(grid.crs or source.crs)
    reproject(
        source.data.astype(np.float32), out,
        src_transform=source.transform, src_crs=crs, src_nodata=np.nan,
        dst_transform=grid.transform, dst_crs=crs, dst_nodata=np.nan,
        resampling=Resampling.max if source.resolution < grid.resolution else Resampling.nearest,
    )
    return out


def landmark_height(dsm: Raster, x: float, y: float, *, search: float, ring: tuple[float, float]) -> dict:
    """Height of a landmark above its surroundings, to check a DSM against a known object.

    The apex is the highest cell within ``search`` of ``(x, y)``; the base is the median
    height of the square ring ``ring[0] < d < ring[1]`` around the apex (``d`` the
    larger of the x and y offsets), just outside the object.

    Parameters
    ----------
    dsm : Raster
    x, y : float
        Where the landmark is, in the DSM's CRS.
    search : float
        Radius of the search for the apex (CRS units).
    ring : (float, float)
        Inner and outer half-widths of the base ring (CRS units).

    Returns
    -------
    dict
        ``apex`` (highest cell above the base), ``top5`` (mean of the five highest cells
        within ``search``, above the base; less sensitive to one spike), ``base``
        (height), ``row`` and ``col`` of the apex cell.
    """
    cx, cy = dsm.cell_centers()
    gx, gy = np.meshgrid(cx, cy)
    z = dsm.data
    near = np.hypot(gx - x, gy - y) < search
    row, col = np.unravel_index(np.nanargmax(np.where(near, z, -np.inf)), z.shape)
    d = np.maximum(np.abs(gx - gx[row, col]), np.abs(gy - gy[row, col]))
    base = float(np.nanmedian(np.where((d > ring[0]) & (d < ring[1]), z, np.nan)))
    top5 = float(np.sort(z[near & np.isfinite(z)])[-5:].mean())
    return {"apex": float(z[row, col]) - base, "top5": top5 - base, "base": base, "row": int(row), "col": int(col)}


def model_check_cells(dsm: Raster, model_dsm: Raster, labels: np.ndarray, vegetated: np.ndarray,
                      filled: np.ndarray) -> np.ndarray:
    """(rows, cols) bool: the building cells on which the model DSM is checked against
    the measured DSM.

    Cells whose top is a tree crown over a roof (``vegetated``: mostly vegetation points) measure
    the tree, not the model; cells filled from their rim (``filled``: no point, LiDAR
    shadow beside walls) measure nothing.
    """
    valid = np.isfinite(dsm.data) & np.isfinite(model_dsm.data)
    return (labels > 0) & valid & ~vegetated & ~filled


def roof_errors(labels: np.ndarray, model_minus_dsm: np.ndarray, n: int) -> np.ndarray:
    """(n,) RMS of the model DSM minus the measured DSM over each building's cells
    (``labels`` 1..n), NaN where a building has no cell with both; in the rasters' units.
    Only the buildings' cells are gathered: the memory follows the buildings, not the grid."""
    if not n:
        return np.zeros(0)
    cells = (labels > 0) & np.isfinite(model_minus_dsm)
    label = labels[cells]
    sums = np.bincount(label, weights=model_minus_dsm[cells] ** 2, minlength=n + 1)[1:n + 1]
    counts = np.bincount(label, minlength=n + 1)[1:n + 1]
    with np.errstate(invalid="ignore"):
        return np.sqrt(sums / counts)
