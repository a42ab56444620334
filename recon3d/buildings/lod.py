"""Building solids by level of detail.

LoD1 is the footprint extruded from the terrain to a representative roof height: a
prism with one ground surface, one roof surface and one wall per footprint edge,
courtyards included. Solids are built in the city model's local frame so that
float32 consumers (glTF, manifold3d) keep millimetres.
"""

from __future__ import annotations

import numpy as np
import shapely

from recon3d.core.city import Solid
from recon3d.core.geo import LocalFrame

__all__ = ["clean_footprint", "lod1_solid"]


def clean_footprint(polygon: shapely.Polygon, tolerance: float) -> shapely.Polygon | None:
    """Footprint ready for extrusion: valid, repeated and collinear vertices removed,
    exterior counter-clockwise and holes clockwise. None when nothing with area is left.
    """
    poly = shapely.make_valid(shapely.remove_repeated_points(polygon, tolerance))
    parts = [g for g in getattr(poly, "geoms", [poly]) if g.geom_type == "Polygon" and g.area > 0]
    if not parts:
        return None
    poly = max(parts, key=lambda g: g.area).simplify(0.0)
    if poly.is_empty or poly.area <= 0 or len(poly.exterior.coords) < 4:
        return None
    return shapely.orient_polygons(poly)


def lod1_solid(footprint: shapely.Polygon, z0: float, z1: float, frame: LocalFrame) -> Solid:
    """The footprint extruded from height ``z0`` to ``z1`` (world heights).

    Parameters
    ----------
    footprint : shapely.Polygon
        Clean polygon (see :func:`clean_footprint`) in world coordinates.
    z0, z1 : float
        Floor and roof heights, ``z1 > z0``.
    frame : LocalFrame

    Returns
    -------
    Solid
        Outward-oriented surfaces: ground, roof, then one wall per edge.
    """
    if not z1 > z0:
        raise ValueError(f"roof height {z1} must be above floor height {z0}")
    rings = [np.asarray(footprint.exterior.coords)[:-1, :2]]
    rings += [np.asarray(r.coords)[:-1, :2] for r in footprint.interiors]
    sizes = [len(r) for r in rings]
    xy = np.concatenate(rings)
    n = len(xy)
    bottom = np.column_stack([xy, np.full(n, z0)])
    top = np.column_stack([xy, np.full(n, z1)])
    vertices = frame.to_local(np.concatenate([bottom, top]))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    ring_idx = [np.arange(s, s + k) for s, k in zip(starts, sizes, strict=True)]

    surfaces = [[r[::-1] for r in ring_idx], [r + n for r in ring_idx]]
    semantics = ["GroundSurface", "RoofSurface"]
    for r in ring_idx:
        nxt = np.roll(r, -1)
        quads = np.column_stack([r, nxt, nxt + n, r + n])
        surfaces += [[q] for q in quads]
        semantics += ["WallSurface"] * len(quads)
    # rings of a valid polygon may touch at a vertex (a courtyard reaching the outline);
    # one shared vertex keeps every edge used exactly twice, so the shell stays closed
    vertices, inverse = np.unique(vertices, axis=0, return_inverse=True)
    surfaces = [[inverse[r] for r in rings] for rings in surfaces]
    return Solid(vertices, surfaces, semantics)
