"""Heights of buildings measured from the DSM and the DTM."""

from __future__ import annotations

import numpy as np
import shapely
from scipy import ndimage

from recon3d.core.raster import Raster

__all__ = ["BuildingHeights", "measure_heights"]


class BuildingHeights:
    """Per-footprint measurements, arrays of length n (NaN where nothing was measured).

    Attributes
    ----------
    ground_z : (n,) float
        Lowest terrain height under the footprint and along its outline.
    roof_z : (n,) float
        Percentile of the DSM cells inside the footprint.
    cells : (n,) int
        Number of DSM cells with data inside the footprint.
    raised_share : (n,) float
        Share of those cells at least ``min_height`` above the terrain.
    """

    def __init__(self, n: int) -> None:
        self.ground_z = np.full(n, np.nan)
        self.roof_z = np.full(n, np.nan)
        self.cells = np.zeros(n, np.int64)
        self.raised_share = np.zeros(n)


def measure_heights(
    footprints: list[shapely.Polygon],
    labels: np.ndarray,
    dsm: Raster,
    dtm: Raster,
    *,
    percentile: float,
    min_height: float,
) -> BuildingHeights:
    """Measure floor and roof heights of each footprint.

    Parameters
    ----------
    footprints : list of shapely.Polygon
    labels : (rows, cols) int
        1 + footprint index per cell (see ``detect.label_footprints``).
    dsm, dtm : Raster
        On one grid.
    percentile : float
        Roof percentile (LoD1 height), e.g. 90.
    min_height : float
        Height (CRS units) a cell needs above the terrain to count as raised.
    """
    out = BuildingHeights(len(footprints))
    ndsm = dsm.data - dtm.data
    for i, sl in enumerate(ndimage.find_objects(labels, max_label=len(footprints))):
        if sl is None:
            continue
        inside = labels[sl] == i + 1
        z = dsm.data[sl][inside]
        valid = np.isfinite(z)
        out.cells[i] = int(valid.sum())
        if valid.any():
            out.roof_z[i] = float(np.percentile(z[valid], percentile))
            out.raised_share[i] = float(np.mean(ndsm[sl][inside][valid] >= min_height))
        out.ground_z[i] = float(np.nanmin(dtm.data[sl][inside])) if inside.any() else np.nan
    if footprints:  # outline samples catch footprints thinner than a cell
        edges = [np.asarray(shapely.segmentize(p.exterior, dsm.resolution).coords)[:, :2] for p in footprints]
        g = dtm.sample(*np.concatenate(edges).T)
        lowest = np.minimum.reduceat(np.where(np.isfinite(g), g, np.inf), np.cumsum([0] + [len(e) for e in edges[:-1]]))
        seen = np.isfinite(lowest)
        out.ground_z[seen] = np.fmin(lowest[seen], out.ground_z[seen])
    return out
