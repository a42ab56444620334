"""Blocks of buildings: the parts detection cut out of one connected roof region,
grouped as one CityJSON Building with its BuildingParts."""

from __future__ import annotations

import logging

import numpy as np
import shapely
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from recon3d.core.city import Building

log = logging.getLogger(__name__)

__all__ = ["assign_blocks"]


def assign_blocks(
    buildings: list[Building],
    labels: np.ndarray,
    raised: np.ndarray,
    *,
    min_shared: float,
    max_gap: float | None = None,
    prefix: str = "block",
) -> int:
    """Mark the parts of split blocks: set :attr:`Building.parent` to a block id.

    Detection splits one connected region of raised cells at height jumps and cuts the
    parts' outlines apart where they overlap, so the parts of one block touch along the
    cut. Two buildings belong to one block when both lie mostly on the same connected
    region of ``raised`` (4-connected, as the split) and their footprints touch: at
    least ``min_shared`` of one's boundary within ``max_gap`` of the other (two houses
    joined only through a rejected tree crown are not a block); blocks are the
    connected groups of such pairs. Only groups of two or more buildings get a parent:
    a block that was not split stays one stand-alone building. Block ids are
    ``block0001``... in the order of each block's first building (skipping ids already
    used by a building).

    Parameters
    ----------
    buildings : list of Building
        ``buildings[i]`` is footprint ``i + 1`` of ``labels``; ``parent`` is overwritten.
    labels : (rows, cols) int
        1 + building index per cell (:func:`recon3d.buildings.detect.label_footprints`).
    raised : (rows, cols) bool
        Raised building cells on the same grid
        (:func:`recon3d.buildings.detect.building_mask`).
    min_shared : float
        Shortest shared boundary (CRS units) that makes two footprints neighbours.
    max_gap : float, optional
        Widest gap (CRS units) between touching footprints; ``min_shared / 2`` by default.

    Returns
    -------
    int
        Number of blocks with two or more parts.
    """
    n = len(buildings)
    for b in buildings:
        b.parent = None
    if n < 2:
        return 0
    regions, _ = ndimage.label(np.asarray(raised, bool))
    labels = np.asarray(labels)
    inside = (labels > 0) & (labels <= n) & (regions > 0)
    region_of = np.zeros(n, np.int64)  # the region under most of each footprint's cells
    if inside.any():
        m = int(regions.max()) + 1
        key = labels[inside].astype(np.int64) * m + regions[inside]
        pairs, counts = np.unique(key, return_counts=True)
        lab, reg = pairs // m, pairs % m
        order = np.lexsort((-counts, lab))
        lab, reg = lab[order], reg[order]
        first = np.r_[True, lab[1:] != lab[:-1]]
        region_of[lab[first] - 1] = reg[first]
    polys = [b.footprint for b in buildings]
    tree = shapely.STRtree(polys)
    tol = min_shared / 2 if max_gap is None else max_gap
    tol = max(tol, 1e-9)
    rows, cols = [], []
    for i, p in enumerate(polys):
        if region_of[i] == 0 or p is None or p.is_empty:
            continue
        for j in tree.query(p, predicate="dwithin", distance=tol):
            if j <= i or region_of[j] != region_of[i]:
                continue
            shared = p.boundary.intersection(polys[j].buffer(tol)).length
            if shared >= min_shared:
                rows.append(i)
                cols.append(int(j))
    if not rows:
        return 0
    graph = sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, comp = csgraph.connected_components(graph, directed=False)
    sizes = np.bincount(comp)
    used = {b.id for b in buildings}
    names: dict[int, str] = {}
    k = 0
    for b, c in zip(buildings, comp, strict=True):
        if sizes[c] < 2:
            continue
        if c not in names:
            k += 1
            while f"{prefix}{k:04d}" in used:
                k += 1
            names[c] = f"{prefix}{k:04d}"
        b.parent = names[c]
    log.info("%d blocks split into %d parts", len(names), int(sum(sizes[sizes >= 2])))
    return len(names)
