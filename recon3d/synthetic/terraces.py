"""Randomised terraced towns with a known older building database, for change detection.

Rows of attached houses (the blocks a LiDAR detection cannot split), trees on open
ground, and an old database mapped house by house with a height attribute, edited to
an earlier state: houses missing from it (new since), houses 6 m lower in it (raised
since), and outlines on open ground (demolished since). The new model holds one
building per row, as detection gives for terraces, so every change inside a block has
to be found at the old database's granularity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import rasterio.features
import shapely
import shapely.affinity
from affine import Affine

from recon3d.core.city import Building, CityModel
from recon3d.core.geo import LocalFrame
from recon3d.core.raster import Raster
from recon3d.io.vectors import Footprint

__all__ = ["TerracedTown", "terraced_town"]

#: Height difference (m) of the raised houses.
RAISED_BY = 6.0


@dataclass
class TerracedTown:
    """A town, its old database and the edits between them.

    Attributes
    ----------
    old : list of Footprint
        The old database (houses minus ``removed``, ``raised`` lower, plus ``demolished``).
    city : CityModel
        The new model: one building per row of houses.
    ndsm, vegetation : Raster
        (rows, cols) float32 nDSM (0.5 m cells, 5 cm noise) and vegetation mask (1 = tree).
    removed : dict of str to shapely.Polygon
        Houses missing from the old database, by id: found as new.
    raised : set of str
        Old ids whose height is ``RAISED_BY`` too low in the old database.
    demolished : set of str
        Old ids on open ground.
    """

    old: list
    city: CityModel
    ndsm: Raster
    vegetation: Raster
    removed: dict
    raised: set
    demolished: set


def terraced_town(seed: int, *, absolute: bool = True, as_text: bool = False, field: str = "roof_height") -> TerracedTown:
    """A random terraced town (200 m square, any orientation, ground 0-300 m above the datum).

    Parameters
    ----------
    seed : int
    absolute : bool
        Old heights above the datum (else above ground).
    as_text : bool
        Old heights written as text ("12.30"), as some databases do.
    field : str
        Name of the old height attribute.
    """
    rng = np.random.default_rng(seed)
    res, size = 0.5, 200.0
    x0, y0, g0 = 400000.0, 6000000.0, float(rng.uniform(0, 300))
    angle = float(rng.uniform(0, 90))
    houses, rows = _rows(rng, x0, y0, size, lambda g: shapely.affinity.rotate(g, angle, origin=(x0 + size / 2, y0 + size / 2)))
    shape = (int(size / res), int(size / res))
    transform = Affine(res, 0, x0, 0, -res, y0 + size)
    ndsm = rasterio.features.rasterize(houses, out_shape=shape, transform=transform, fill=0, dtype="float32")
    ndsm += rng.normal(0, 0.05, shape).astype(np.float32)
    built = shapely.union_all([p for p, _ in houses])
    trees = _scatter(rng, x0, y0, size, 8, lambda c: c.buffer(rng.uniform(3, 6)), built, gap=0.5)
    crowns = rasterio.features.rasterize([(t, 1) for t in trees], out_shape=shape, transform=transform, fill=0,
                                         dtype="uint8") > 0
    ndsm[crowns] = rng.uniform(8, 15, crowns.sum())
    new = []
    for k, row in enumerate(rows):
        outline = shapely.union_all([houses[i][0] for i in row]).buffer(rng.uniform(0.2, 0.4), join_style="mitre")
        top = float(np.percentile([houses[i][1] for i in row], 90))
        new.append(Building(f"b{k:04d}", outline, g0, g0 + top, {}, "ok", None, {}))
    n = len(houses)
    order = rng.permutation(n).tolist()
    k_removed, k_raised = max(1, n // 10), max(1, 8 * n // 100)
    removed, raised = set(order[:k_removed]), set(order[k_removed:k_removed + k_raised])
    shift = rng.uniform(-0.5, 0.5, 2)  # map-to-data shift of the old database

    def value(v: float):
        return f"{v:.2f}" if as_text else round(v, 2)

    old = [Footprint(f"h{i:03d}", shapely.affinity.translate(p, *shift),
                     {field: value((g0 if absolute else 0.0) + h - (RAISED_BY if i in raised else 0.0))})
           for i, (p, h) in enumerate(houses) if i not in removed]
    fakes = _scatter(rng, x0, y0, size, 3, lambda c: c.buffer(5, cap_style="square"), shapely.union_all([built, *trees]),
                     gap=3.0)
    old += [Footprint(f"fake{k + 1}", f, {field: value((g0 if absolute else 0.0) + 8.0)}) for k, f in enumerate(fakes)]
    return TerracedTown(
        old, CityModel(new, None, LocalFrame((x0, y0, g0))), Raster(ndsm, transform),
        Raster(crowns.astype(np.float32), transform), {f"h{i:03d}": houses[i][0] for i in sorted(removed)},
        {f"h{i:03d}" for i in raised}, {f"fake{k + 1}" for k in range(len(fakes))},
    )


def _rows(rng, x0, y0, size, place) -> tuple[list[tuple[shapely.Polygon, float]], list[list[int]]]:
    """Rows of 4-9 attached houses (5-9 m wide, 8-12 m deep, 6-12 m high; a third of
    them 2.5-5 m higher or lower than their row, none under 3.5 m)."""
    houses, rows = [], []
    y = y0 + 30
    while y < y0 + size - 40:
        depth, width, base = rng.uniform(8, 12), rng.uniform(5, 9), rng.uniform(6, 12)
        x, row = x0 + rng.uniform(25, 40), []
        for _ in range(int(rng.integers(4, 10))):
            w = width + rng.uniform(-1, 1)
            step = rng.choice([-1, 1]) * rng.uniform(2.5, 5) if rng.random() < 0.3 else rng.uniform(-0.5, 0.5)
            row.append(len(houses))
            houses.append((place(shapely.box(x, y, x + w, y + depth)), max(float(base + step), 3.5)))
            x += w
        rows.append(row)
        y += depth + rng.uniform(12, 20)
    return houses, rows


def _scatter(rng, x0, y0, size, count, make, avoid, gap) -> list:
    """``count`` shapes ``make(centre)`` at random, each at least ``gap`` from ``avoid`` and from each other."""
    out: list = []
    while len(out) < count:
        shape = make(shapely.Point(rng.uniform(x0 + 10, x0 + size - 10), rng.uniform(y0 + 10, y0 + size - 10)))
        if shape.distance(avoid) >= gap and all(shape.distance(o) >= gap for o in out):
            out.append(shape)
    return out
