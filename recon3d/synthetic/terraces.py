"""Randomised terraced towns with a known older building database, for change detection.

Rows of attached houses (the blocks a LiDAR detection cannot split), trees on open
ground, and an old database mapped house by house with a height attribute, edited to
an earlier state: houses missing from it (new since), houses 6 m lower in it (raised
since), and outlines on open ground (demolished since). The new model holds one
building per row, as detection gives for terraces, so every change inside a block has
to be found at the old database's granularity.

With ``mix=True`` the houses of a row differ as real terraces do (:func:`_mixed_rows`):
some as high as their neighbour, most 0.5-4 m higher or lower, flat roofs or gable
roofs with the ridge along or across the row, some with a dormer; ``houses`` holds
every true house, the ground truth of splitting blocks into buildings
(``scripts/bench_blocks.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
    houses : list of (shapely.Polygon, float)
        Every true house: its outline and its highest point above ground (m).
    parted : list of bool
        Per house, whether its roof tells it apart from the house before it in its row
        (a different height, or gables side by side meeting in a valley), or it starts
        a row: what a split at every true step and valley would cut.
    """

    old: list
    city: CityModel
    ndsm: Raster
    vegetation: Raster
    removed: dict
    raised: set
    demolished: set
    houses: list = field(default_factory=list)
    parted: list = field(default_factory=list)


def terraced_town(
    seed: int, *, absolute: bool = True, as_text: bool = False, field: str = "roof_height", mix: bool = False
) -> TerracedTown:
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
    mix : bool
        Houses as real terraces mix them (:func:`_mixed_rows`) rather than rows of
        nearly equal flat roofs with a third of the houses 2.5-5 m off.
    """
    rng = np.random.default_rng(seed)
    res, size = 0.5, 200.0
    x0, y0, g0 = 400000.0, 6000000.0, float(rng.uniform(0, 300))
    angle = float(rng.uniform(0, 90))
    origin = (x0 + size / 2, y0 + size / 2)
    shape = (int(size / res), int(size / res))
    transform = Affine(res, 0, x0, 0, -res, y0 + size)
    if mix:
        houses, rows, ndsm, parted = _mixed_rows(rng, x0, y0, size, angle, origin, shape, transform)
    else:
        houses, rows = _rows(rng, x0, y0, size, lambda g: shapely.affinity.rotate(g, angle, origin=origin))
        ndsm = rasterio.features.rasterize(houses, out_shape=shape, transform=transform, fill=0, dtype="float32")
        parted = [k == 0 or houses[i][1] != houses[i - 1][1] for row in rows for k, i in enumerate(row)]
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
        {f"h{i:03d}" for i in raised}, {f"fake{k + 1}" for k in range(len(fakes))}, houses, parted,
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


#: Roof kinds of a mixed row and their shares: flat, gable with the ridge along the row,
#: gable with the ridge across it (a valley between each pair of houses).
ROOF_KINDS = (("flat", 0.3), ("along", 0.5), ("across", 0.2))


def _mixed_rows(rng, x0, y0, size, angle, origin, shape, transform):
    """Rows of 4-9 attached houses as real terraces mix them, rasterised with their roofs.

    Each house is 5-9 m wide and 8-12 m deep; its eaves are, with a chance of 0.3, as
    high as its left neighbour's (the same roof: no height tells them apart), else
    0.5-4 m higher or lower (3.5-14 m above ground). A row has one roof kind
    (:data:`ROOF_KINDS`); a gable rises 2-5 m above the eaves (varying by up to 0.5 m
    from house to house, none when the eaves are equal) and a fifth of the houses under
    one along the row carry a dormer (2-3 m wide, 1.5-2.5 m out of the front slope).

    Returns
    -------
    houses : list of (shapely.Polygon, float)
        Outline and highest point of each house.
    rows : list of list of int
    ndsm : (rows, cols) float32
        The roofs' heights above ground, 0 elsewhere (no noise yet).
    parted : list of bool
        :attr:`TerracedTown.parted`.
    """
    boxes, params, rows = [], [], []
    kinds, shares = zip(*ROOF_KINDS, strict=True)
    y = y0 + 30
    while y < y0 + size - 40:
        depth, width = rng.uniform(8, 12), rng.uniform(5, 9)
        kind = kinds[int(rng.choice(len(kinds), p=shares))]
        eave, rise = rng.uniform(5, 10), (rng.uniform(2, 5) if kind != "flat" else 0.0)
        x, row = x0 + rng.uniform(25, 40), []
        for k in range(int(rng.integers(4, 10))):
            w = width + rng.uniform(-1, 1)
            if k and rng.random() >= 0.3:
                eave = float(np.clip(eave + rng.choice([-1, 1]) * rng.uniform(0.5, 4), 3.5, 14))
                if kind != "flat":
                    rise = float(np.clip(rise + rng.uniform(-0.5, 0.5), 1.5, 5.5))
            dormer = kind == "along" and rng.random() < 0.2
            dw, dd = rng.uniform(2, 3), rng.uniform(1.5, 2.5)
            row.append(len(boxes))
            boxes.append((x, y, x + w, y + depth))
            params.append((kind, eave, rise, dormer, dw, dd))
            x += w
        rows.append(row)
        y += depth + rng.uniform(12, 20)
    houses = [
        (shapely.affinity.rotate(shapely.box(*b), angle, origin=origin), e + r) for b, (_, e, r, *_) in zip(boxes, params, strict=True)
    ]
    index = rasterio.features.rasterize(
        [(p, i + 1) for i, (p, _) in enumerate(houses)], out_shape=shape, transform=transform, fill=0, dtype="int32"
    )
    r, c = np.nonzero(index)
    i = index[r, c] - 1
    wx, wy = transform * (c + 0.5, r + 0.5)
    # cell centres back in the unrotated frame of the rows
    t = np.radians(angle)
    dx, dy = wx - origin[0], wy - origin[1]
    lx = origin[0] + dx * np.cos(t) + dy * np.sin(t)
    ly = origin[1] - dx * np.sin(t) + dy * np.cos(t)
    b = np.asarray(boxes, np.float64)[i]
    kind = np.array([p[0] for p in params])[i]
    eave, rise = np.array([p[1] for p in params])[i], np.array([p[2] for p in params])[i]
    xm, ym = (b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2
    hw, hd = (b[:, 2] - b[:, 0]) / 2, (b[:, 3] - b[:, 1]) / 2
    along = np.clip(1 - np.abs(ly - ym) / hd, 0, 1)
    across = np.clip(1 - np.abs(lx - xm) / hw, 0, 1)
    z = eave + rise * np.select([kind == "along", kind == "across"], [along, across], 0.0)
    dormer = np.array([p[3] for p in params])[i]
    dw, dd = np.array([p[4] for p in params])[i], np.array([p[5] for p in params])[i]
    # a dormer on the front slope: a flat box from the eaves' side up to half the ridge height
    on = dormer & (np.abs(lx - xm) <= dw / 2) & (ly >= b[:, 1] + hd - dd - 1.0) & (ly <= b[:, 1] + hd - 1.0)
    z = np.where(on, np.maximum(z, eave + rise * 0.6), z)
    ndsm = np.zeros(shape, np.float32)
    ndsm[r, c] = z
    parted = [k == 0 or params[i][0] == "across" or params[i][1:3] != params[i - 1][1:3]
              for row in rows for k, i in enumerate(row)]
    return houses, rows, ndsm, parted


def _scatter(rng, x0, y0, size, count, make, avoid, gap) -> list:
    """``count`` shapes ``make(centre)`` at random, each at least ``gap`` from ``avoid`` and from each other."""
    out: list = []
    while len(out) < count:
        shape = make(shapely.Point(rng.uniform(x0 + 10, x0 + size - 10), rng.uniform(y0 + 10, y0 + size - 10)))
        if shape.distance(avoid) >= gap and all(shape.distance(o) >= gap for o in out):
            out.append(shape)
    return out
