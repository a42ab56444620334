"""Change detection of a newly derived city model against an older building database.

The old database (footprints with optional heights and roof types) is matched to the
buildings of a run by area overlap: an old and a new outline are linked when one of
them, shrunk by the planimetric tolerance ``shift`` (1 m by default), still overlaps the
other by more than ``overlap_share`` of its area; each connected component of this
bipartite graph is one *group* ("1:1", "1:m" split, "n:1" merge, "n:m"; "1:0" and "0:1"
for unmatched ones). Groups, not pairs, are compared, so a row of houses captured as
one block or a building mapped as two parts is not a change. Shrinking before linking
keeps a shifted building from being linked to its neighbour, and footprints are
compared within the same tolerance, so the usual map-to-data shift (and roof overhangs
that LiDAR outlines include and wall-based maps do not) are not changes either.

Classes (one per record of :attr:`ChangeResult.changes`) and their raster codes:

===================  ====  ===========================================================
unchanged            0     matched group, no difference beyond the thresholds
new                  1     new building(s) without an old counterpart
demolished           2     old building(s) without a new counterpart and no building
                           evidence in the nDSM where the data exist
height_changed       3     roof height differs by more than ``height_threshold``
footprint_changed    4     area or shape differs (``subtype`` extension / partial_demolition
                           / reshaped)
roof_changed         5     LoD2 roof type differs (only when both sides have one)
not_observed         6     old building(s) where the data do not cover enough of the
                           outline to decide (no data is not no building)
===================  ====  ===========================================================

When a group has several differences, ``class`` is the first of footprint, height,
roof, and ``flags`` lists them all.

Evidence and confidence: for every group the nDSM cells inside the outlines give the
*coverage* (share of the outline with data; cells outside the grid count as missing)
and the *support* (share of covered cells higher than ``min_height``). Optional
rasters add vegetation cover (share of vegetated cells, which lowers confidence: trees
hide or mimic buildings) and point density (below ``min_density`` lowers confidence).
The confidence in [0, 1] is coverage x evidence strength x margin beyond the threshold
(see :func:`_confidence`).

All thresholds are in metres and m2 and converted with :class:`~recon3d.core.geo.Units`.
Pure functions: the caller writes the files.
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from recon3d.core.city import Building, CityModel
from recon3d.core.geo import Units
from recon3d.core.raster import Raster
from recon3d.errors import InputError

log = logging.getLogger(__name__)

__all__ = [
    "CHANGE_CODES",
    "ChangeParams",
    "ChangeResult",
    "change_features",
    "change_raster",
    "detect_changes",
    "match_groups",
    "point_density",
    "updated_model",
]

#: Integer code of every change class in :func:`change_raster` (float32, NaN elsewhere).
CHANGE_CODES: dict[str, int] = {
    "unchanged": 0,
    "new": 1,
    "demolished": 2,
    "height_changed": 3,
    "footprint_changed": 4,
    "roof_changed": 5,
    "not_observed": 6,
}

#: Attribute names (case-insensitive) holding an absolute roof height in the old
#: database (3DBAG's ``b3_h_dak_*`` and AHN's ``h_dak_*`` are heights above NAP).
ROOF_Z_FIELDS = ("roof_z", "z_roof", "altitude_toit", "z_max", "zmax", "z_max_toit", "h_dak_max", "h_dak_70p",
                 "h_dak_50p", "b3_h_dak_max", "b3_h_dak_70p", "b3_h_dak_50p", "absolute_height")
#: Attribute names holding a height above ground.
HEIGHT_FIELDS = ("height", "hauteur", "measuredheight", "h_building", "building_height", "bldg_height", "hoogte",
                 "height_above_ground", "relative_height")
#: Attribute names whose reference (ground or datum) databases do not agree on: it is
#: decided from the data (see :func:`_resolve_reference`).
AMBIGUOUS_HEIGHT_FIELDS = ("roof_height", "roofheight", "h_roof", "max_height", "z")
#: Metres per foot, for heights written with a unit ("35 ft").
_FOOT = 0.3048


@dataclass(frozen=True)
class ChangeParams:
    """Thresholds of change detection (metres, m2 and shares in [0, 1]).

    Attributes
    ----------
    overlap_share : float
        An old and a new outline are linked when one of them, shrunk by ``shift``,
        overlaps the other by more than this share of its shrunk area.
    shift : float
        Planimetric tolerance (m): outlines are compared after buffering by this much,
        so a map-to-data shift up to ``shift`` is not a footprint change.
    height_threshold : float
        Roof height difference (m) that makes a height change.
    area_threshold : float
        Relative area difference that makes a footprint change, counted beyond what
        the old outline grown or shrunk by ``shift`` explains (roof overhangs seen by
        LiDAR, digitising on walls or eaves).
    shape_threshold : float
        Share of the larger outline outside the other (each buffered by ``shift``)
        that makes a footprint change.
    min_height : float
        nDSM height (m) above which a cell is building evidence.
    min_support : float
        Share of covered cells above ``min_height`` needed to say something stands there.
    min_coverage : float
        Share of an outline with nDSM data needed to decide at all; below it an old
        building is "not_observed", never "demolished".
    min_new_area : float
        New buildings smaller than this (m2) are not reported as new.
    min_density : float
        Point density (points/m2) below which confidence drops (when a density raster is given).
    block_new_area, block_new_height : float
        A region of building evidence inside a matched block but outside every old
        outline (grown by ``shift``) is a new building when it covers at least
        ``block_new_area`` (m2) at ``block_new_height`` (m) or more: the old database
        mapped the block house by house, and one house is missing from it.
    extension_share : float
        Such a region touching one old building only, smaller than this share of its
        area, is that building's extension (a footprint change), not a new building.
    height_field : str, optional
        Name of the old database's height attribute, when none of the usual names.
    height_reference : {"ground", "absolute"}, optional
        What the old heights are measured from; by default known from the attribute's
        name, or decided from the data for ambiguous names (``roof_height``).
    """

    overlap_share: float = 0.1
    shift: float = 1.0
    height_threshold: float = 2.0
    area_threshold: float = 0.15
    shape_threshold: float = 0.15
    min_height: float = 2.0
    min_support: float = 0.3
    min_coverage: float = 0.5
    min_new_area: float = 4.0
    min_density: float = 2.0
    block_new_area: float = 25.0
    block_new_height: float = 2.5
    extension_share: float = 0.5
    height_field: str | None = None
    height_reference: str | None = None

    def __post_init__(self) -> None:
        if self.height_reference not in (None, "ground", "absolute"):
            raise InputError(f"old height reference {self.height_reference!r}: choose ground or absolute")


@dataclass
class ChangeResult:
    """Outcome of :func:`detect_changes`.

    Attributes
    ----------
    changes : list of dict
        One record per group: ``class``, ``flags``, ``confidence``, ``match``
        ("1:1", "1:n", "n:1", "n:m", "0:1", "1:0"...), ``old_ids``, ``new_ids``,
        ``geometry`` (shapely; the new outlines, or the old ones when nothing new),
        ``subtype`` for footprint changes, measured values (``old_area``,
        ``new_area`` in m2; ``iou``, ``shape_share``, ``area_change``,
        ``area_change_beyond_shift`` as shares; ``old_roof_z``, ``new_roof_z``,
        ``old_height``, ``new_height`` in CRS height units; ``dh`` new minus old in
        metres; ``old_roof_type``, ``new_roof_type``) and evidence (``coverage``,
        ``support``, ``vegetation``, ``density``, ``ndsm_height`` in metres).
        Values missing on one side are None.
    summary : dict of str to int
        Number of records per class (every class present, zeros included).
    notes : list of str
        Repairs, skipped checks and other remarks for run.json / the report.
    warnings : list of str
        What the user must see (terminal, report): no heights found, heights that
        disagree with the data.
    """

    changes: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- inputs


def _clean_old(old: list, notes: list[str]) -> tuple[list[str], np.ndarray, list[dict]]:
    """Ids, valid polygons (n,) and attributes of the old database; repairs noted."""
    ids, polys, attrs = [], [], []
    seen: Counter = Counter()
    for item in old:
        geom = item.polygon
        if geom is None or geom.is_empty:
            notes.append(f"old building {item.id}: empty geometry skipped")
            continue
        if not geom.is_valid:
            geom = shapely.make_valid(geom)
            notes.append(f"old building {item.id}: invalid polygon repaired")
        parts = [p for p in shapely.get_parts(geom) if p.geom_type == "Polygon" and p.area > 0]
        if not parts:
            notes.append(f"old building {item.id}: no area, skipped")
            continue
        geom = shapely.union_all(parts) if len(parts) > 1 else parts[0]
        fid = str(item.id)
        seen[fid] += 1
        if seen[fid] > 1:
            fid = f"{fid}#{seen[fid]}"
            notes.append(f"old building id {item.id} repeated; renamed {fid}")
        ids.append(fid)
        polys.append(geom)
        attrs.append(dict(getattr(item, "attributes", {}) or {}))
    return ids, np.array(polys, dtype=object), attrs


def _new_buildings(city: CityModel, notes: list[str]) -> list[Building]:
    """Buildings of the run that stand as evidence (a solid was built, an outline with area)."""
    kept = [
        b
        for b in city.buildings
        if b.status != "failed" and b.footprint is not None and b.footprint.area > 0
    ]
    if len(kept) < len(city.buildings):
        notes.append(
            f"{len(city.buildings) - len(kept)} buildings of the new model without a result "
            "(failed or empty) are not used as evidence"
        )
    return kept


class OldHeights(NamedTuple):
    """Heights of the old buildings as read from their attributes."""

    values: np.ndarray  # (n,) float, CRS height units, NaN where absent
    field: str | None  # the attribute they came from (the most common one)
    reference: str | None  # "ground", "absolute" or "auto" (decided from the data)


def _old_heights(attrs: list[dict], params: ChangeParams, units: Units) -> OldHeights:
    """The old buildings' heights: ``params.height_field`` or the first usual name found."""
    names = ((params.height_field.lower(),) if params.height_field else
             ROOF_Z_FIELDS + HEIGHT_FIELDS + AMBIGUOUS_HEIGHT_FIELDS)
    values = np.full(len(attrs), np.nan)
    used: Counter = Counter()
    for i, a in enumerate(attrs):
        low = {str(k).lower(): v for k, v in a.items()}
        for name in names:
            v = _number(low.get(name), units)
            if np.isfinite(v):
                values[i] = v
                used[name] += 1
                break
    if not used:
        return OldHeights(values, None, None)
    field_name = used.most_common(1)[0][0]
    if params.height_reference:
        reference = params.height_reference
    elif field_name in ROOF_Z_FIELDS:
        reference = "absolute"
    elif field_name in HEIGHT_FIELDS:
        reference = "ground"
    else:
        reference = "auto"
    return OldHeights(values, field_name, reference)


def _number(value, units: Units) -> float:
    """A height from an attribute value: a number, or text such as "12.5", "12,5 m", "41 ft"."""
    if isinstance(value, bool) or value is None:
        return float("nan")
    if isinstance(value, int | float | np.number):
        return float(value)
    match = re.fullmatch(r"\s*([-+]?\d+(?:[.,]\d+)?)\s*(m|ft|feet|')?\s*", str(value))
    if not match:
        return float("nan")
    v = float(match.group(1).replace(",", "."))
    return units.height(v * _FOOT) if match.group(2) in ("ft", "feet", "'") else v


def _first_number(attrs: dict, names: tuple[str, ...]) -> float:
    for n in names:
        v = attrs.get(n)
        try:
            v = float(v)
        except (TypeError, ValueError):
            continue
        if np.isfinite(v):
            return v
    return float("nan")


# --------------------------------------------------------------------------- matching


def match_groups(
    old_polys: np.ndarray, new_polys: np.ndarray, overlap_share: float, shift: float = 0.0
) -> list[tuple[list[int], list[int]]]:
    """Connected components of the old-new overlap graph.

    An old and a new outline are linked when one of them, shrunk by ``shift``, still
    overlaps the other by more than ``overlap_share`` of its (shrunk) area. Shrinking
    first keeps a map-to-data shift of a building from linking it to its neighbour.

    Parameters
    ----------
    old_polys : (n,) shapely Polygons
    new_polys : (m,) shapely Polygons
    overlap_share : float
        Minimum overlap as a share of the shrunk polygon's area.
    shift : float
        Planimetric tolerance in CRS units (0: plain overlap of the smaller polygon).

    Returns
    -------
    list of (old indices, new indices)
        One entry per component, including unmatched singletons (one side empty).
    """
    n, m = len(old_polys), len(new_polys)
    oi, ni = (np.zeros(0, np.int64),) * 2
    if n and m:
        tree = shapely.STRtree(new_polys)
        oi, ni = tree.query(old_polys, predicate="intersects")
    if len(oi):
        old_core, new_core = _shrink(old_polys, shift), _shrink(new_polys, shift)
        inter_old = shapely.area(shapely.intersection(old_core[oi], new_polys[ni]))
        inter_new = shapely.area(shapely.intersection(old_polys[oi], new_core[ni]))
        keep = inter_old > overlap_share * shapely.area(old_core[oi])
        keep |= inter_new > overlap_share * shapely.area(new_core[ni])
        oi, ni = oi[keep], ni[keep]
    graph = coo_matrix((np.ones(len(oi)), (oi, n + ni)), shape=(n + m, n + m))
    count, label = connected_components(graph, directed=False)
    order = np.argsort(label, kind="stable")
    bounds = np.searchsorted(label[order], np.arange(count + 1))
    groups = []
    for k in range(count):
        members = order[bounds[k] : bounds[k + 1]]
        groups.append(([int(i) for i in members if i < n], [int(i - n) for i in members if i >= n]))
    return groups


def _shrink(polys: np.ndarray, shift: float) -> np.ndarray:
    """Polygons (n,) eroded by ``shift``; by half of it, or not at all, where that empties them."""
    if shift <= 0:
        return polys
    out = shapely.buffer(polys, -shift, join_style="mitre")
    half = shapely.buffer(polys, -shift / 2, join_style="mitre")
    out = np.where(shapely.area(out) > 0, out, half)
    return np.where(shapely.area(out) > 0, out, polys)


# --------------------------------------------------------------------------- evidence


def _cells(geom, raster: Raster) -> tuple[np.ndarray, np.ndarray, float]:
    """Grid cells whose centre lies in ``geom``.

    Returns
    -------
    rows, cols : (k,) int
        Cells inside both the outline and the grid.
    expected : float
        Number of cell centres inside the outline on the grid extended without
        bounds (at least 1), so that cells off the grid count as missing data.
    """
    rows, cols = raster.shape
    xmin, ymin, xmax, ymax = geom.bounds
    (r0, r1), (c0, c1) = raster.rowcol(np.array([xmin, xmax]), np.array([ymax, ymin]))
    r0, r1 = max(int(r0), 0), min(int(r1), rows - 1)
    c0, c1 = max(int(c0), 0), min(int(c1), cols - 1)
    rr, cc = np.mgrid[r0 : max(r1, r0 - 1) + 1, c0 : max(c1, c0 - 1) + 1]
    x = raster.transform.c + (cc + 0.5) * raster.transform.a
    y = raster.transform.f + (rr + 0.5) * raster.transform.e
    inside = shapely.contains_xy(geom, x, y)
    off_grid = shapely.difference(geom, shapely.box(*raster.bounds)).area / raster.resolution**2
    expected = float(inside.sum()) + off_grid
    if not inside.any():  # smaller than a cell, or off the grid: the cell under one point
        p = geom.representative_point()
        r, c = raster.rowcol(np.array([p.x]), np.array([p.y]))
        ok = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
        return r[ok], c[ok], max(expected, 1.0)
    return rr[inside], cc[inside], max(expected, 1.0)


def evidence(
    geom,
    ndsm: Raster,
    min_height: float,
    vegetation: Raster | None = None,
    density: Raster | None = None,
) -> dict[str, float | None]:
    """nDSM evidence inside one outline.

    Returns
    -------
    dict
        ``coverage`` share of the outline with nDSM data, ``support`` share of covered
        cells above ``min_height`` (vegetated cells excluded when ``vegetation`` is
        given), ``vegetation`` share of covered cells flagged as vegetation (or None),
        ``density`` median point density inside (or None), ``ndsm_height`` 90th
        percentile of the nDSM inside (CRS height units, NaN without data).
    """
    r, c, expected = _cells(geom, ndsm)
    values = ndsm.data[r, c]
    valid = np.isfinite(values)
    coverage = float(min(valid.sum() / expected, 1.0))
    out: dict[str, float | None] = {
        "coverage": coverage,
        "support": 0.0,
        "vegetation": None,
        "density": None,
    }
    high = valid & (values > min_height)
    if vegetation is not None:
        veg = np.nan_to_num(vegetation.data[r, c]) > 0.5
        out["vegetation"] = float(veg[valid].mean()) if valid.any() else None
        high &= ~veg
    out["support"] = float(high.sum() / valid.sum()) if valid.any() else 0.0
    if density is not None:
        d = density.data[r, c]
        out["density"] = float(np.nanmedian(d)) if np.isfinite(d).any() else 0.0
    out["ndsm_height"] = float(np.percentile(values[valid], 90)) if valid.any() else float("nan")
    return out


def point_density(xyz: np.ndarray, grid: Raster) -> Raster:
    """Points per CRS unit2 in every cell of ``grid``, for :func:`detect_changes`.

    Parameters
    ----------
    xyz : (n, 2+) float
        Point coordinates (a :class:`~recon3d.core.pointcloud.PointCloud`'s ``xyz``).
    grid : Raster
        The product grid (the nDSM's).

    Returns
    -------
    Raster
        (rows, cols) float32 density, 0 where no point fell.
    """
    rows, cols = grid.shape
    r, c = grid.rowcol(xyz[:, 0], xyz[:, 1])
    ok = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
    counts = np.bincount(r[ok] * cols + c[ok], minlength=rows * cols).reshape(rows, cols)
    return grid.like(counts / grid.resolution**2, product="point density")


def _confidence(ev: dict, strength: float, params: ChangeParams, units: Units) -> float:
    """coverage x strength x (1 - vegetation / 2) x density factor, in [0, 1].

    ``strength`` says how clearly the measured value clears (or stays within) its
    threshold, in [0, 1].
    """
    conf = ev["coverage"] * float(np.clip(strength, 0.0, 1.0))
    if ev.get("vegetation") is not None:
        conf *= 1.0 - 0.5 * ev["vegetation"]
    if ev.get("density") is not None:
        need = params.min_density * units.horizontal**2  # points per CRS unit2
        conf *= float(min(ev["density"] / need, 1.0)) if need > 0 else 1.0
    return round(float(conf), 3)


def _margin(value: float, threshold: float, changed: bool) -> float:
    """0.5 at the threshold, 1 at twice (or zero) the threshold."""
    if not np.isfinite(value) or threshold <= 0:
        return 0.5
    ratio = abs(value) / threshold
    return float(np.clip(0.5 + 0.5 * ((ratio - 1.0) if changed else (1.0 - ratio)), 0.0, 1.0))


# --------------------------------------------------------------------------- comparison


def _compare_footprints(old_u, new_u, shift: float) -> dict[str, float]:
    """Area, IoU and tolerant shape difference of two outline unions (CRS units)."""
    a_old, a_new = old_u.area, new_u.area
    union = shapely.union(old_u, new_u).area
    iou = shapely.intersection(old_u, new_u).area / union if union > 0 else 0.0
    grown = shapely.buffer(old_u, shift, join_style="mitre")
    out_new = shapely.difference(new_u, grown).area
    out_old = shapely.difference(old_u, shapely.buffer(new_u, shift, join_style="mitre")).area
    shape = (out_new + out_old) / max(a_old, a_new)
    # area change beyond what an outline drawn up to `shift` wider or narrower explains
    low, high = shapely.buffer(old_u, -shift, join_style="mitre").area, grown.area
    tolerant = 0.0
    if a_new > high:
        tolerant = (a_new - high) / high
    elif a_new < low:
        tolerant = (a_new - low) / a_old
    return {
        "old_area": a_old,
        "new_area": a_new,
        "area_change": (a_new - a_old) / a_old if a_old > 0 else float("inf"),
        "area_change_beyond_shift": tolerant,
        "iou": iou,
        "shape_share": shape,
        "added_area": out_new,
        "removed_area": out_old,
    }


def _weighted(values: np.ndarray, weights: np.ndarray) -> float:
    ok = np.isfinite(values)
    if not ok.any():
        return float("nan")
    return float(np.average(values[ok], weights=weights[ok]))


def _group_record(
    oi: list[int],
    ni: list[int],
    ctx: dict[str, Any],
) -> dict[str, Any]:
    """Classify one matched group (both sides non-empty)."""
    p, u = ctx["params"], ctx["units"]
    old_u = shapely.union_all(ctx["old_polys"][oi])
    new_b = [ctx["new"][j] for j in ni]
    new_u = shapely.union_all([b.footprint for b in new_b])
    carved = ctx.get("carved")
    if carved is not None and new_u.intersects(carved):  # new houses of the block are records of their own
        new_u = shapely.difference(new_u, carved)
    fp = _compare_footprints(old_u, new_u, u.length(p.shift))
    ev = evidence(new_u, ctx["ndsm"], u.height(p.min_height), ctx["vegetation"], ctx["density"])
    rec = _base(oi, ni, ctx, new_u, fp, ev)
    flags, strengths = [], []
    da = fp["area_change_beyond_shift"]
    fp_changed = abs(da) > p.area_threshold or fp["shape_share"] > p.shape_threshold
    margins = (
        _margin(da, p.area_threshold, fp_changed),
        _margin(fp["shape_share"], p.shape_threshold, fp_changed),
    )
    fp_strength = max(margins) if fp_changed else min(margins)
    if fp_changed:
        flags.append("footprint_changed")
        grew = fp["added_area"] > 0.5 * fp["removed_area"]
        shrank = fp["removed_area"] > 0.5 * fp["added_area"]
        subtype = "extension" if grew else "partial_demolition"
        rec["subtype"] = "reshaped" if grew and shrank else subtype
        strengths.append(fp_strength)
    dh = _height_difference(rec)
    if np.isfinite(dh):
        rec["dh"] = dh * u.vertical
        # several old buildings under one new block are compared one by one (_block_height_records)
        h_changed = abs(dh) > u.height(p.height_threshold) and len(oi) == 1
        if h_changed:
            flags.append("height_changed")
            strengths.append(_margin(dh, u.height(p.height_threshold), True))
    if _roof_changed(rec, len(oi), len(ni)):
        flags.append("roof_changed")
        strengths.append(0.7)
    rec["flags"] = ",".join(flags)
    rec["class"] = flags[0] if flags else "unchanged"
    if not flags:
        strengths.append(fp_strength)
        if np.isfinite(rec.get("dh", np.nan)):
            strengths.append(_margin(rec["dh"] / u.vertical, u.height(p.height_threshold), False))
    support = min(ev["support"] / max(p.min_support, 1e-9), 1.0)
    rec["confidence"] = _confidence(ev, min(min(strengths), support), p, u)
    return rec


def _base(oi, ni, ctx, geometry, fp, ev) -> dict[str, Any]:
    """Record fields common to every class: ids, geometry, values in metres."""
    u = ctx["units"]
    old_areas = shapely.area(ctx["old_polys"][oi]) if oi else np.zeros(0)
    new_b = [ctx["new"][j] for j in ni]
    new_areas = np.array([b.footprint.area for b in new_b])
    old_types = {ctx["old_attrs"][i].get("roof_type") for i in oi} - {None, ""}
    new_types = {b.attributes.get("roof_type") for b in new_b} - {None, ""}
    rec: dict[str, Any] = {
        "class": "unchanged",
        "flags": "",
        "confidence": 0.0,
        "match": f"{_card(len(oi), 'n')}:{_card(len(ni), 'm')}",
        "old_ids": [ctx["old_ids"][i] for i in oi],
        "new_ids": [b.id for b in new_b],
        "geometry": geometry,
        "old_area": _m2(float(old_areas.sum()), u) if oi else None,
        "new_area": _m2(float(new_areas.sum()), u) if ni else None,
        "old_roof_z": _weighted(ctx["old_roof"][oi], old_areas) if oi else float("nan"),
        "old_height": _weighted(ctx["old_height"][oi], old_areas) if oi else float("nan"),
        "new_roof_z": _weighted(np.array([b.roof_z for b in new_b]), new_areas),
        "new_height": _weighted(np.array([b.height for b in new_b]), new_areas),
        "old_roof_type": ",".join(sorted(map(str, old_types))) or None,
        "new_roof_type": ",".join(sorted(map(str, new_types))) or None,
        "coverage": round(ev["coverage"], 3),
        "support": round(ev["support"], 3),
        "vegetation": ev["vegetation"],
        "density": ev["density"],
        "ndsm_height": ev["ndsm_height"] * u.vertical if np.isfinite(ev["ndsm_height"]) else None,
    }
    if fp:
        rec["iou"] = round(fp["iou"], 3)
        rec["shape_share"] = round(fp["shape_share"], 3)
        rec["area_change"] = round(fp["area_change"], 3)
        rec["area_change_beyond_shift"] = round(fp["area_change_beyond_shift"], 3)
    return rec


def _card(k: int, many: str) -> str:
    return str(k) if k <= 1 else many


def _m2(area: float, units: Units) -> float:
    return round(area * units.horizontal**2, 2)


def _height_difference(rec: dict) -> float:
    """New minus old roof height (CRS units): absolute roof z when the old has it, else height."""
    if np.isfinite(rec["old_roof_z"]) and np.isfinite(rec["new_roof_z"]):
        return rec["new_roof_z"] - rec["old_roof_z"]
    if np.isfinite(rec["old_height"]) and np.isfinite(rec["new_height"]):
        return rec["new_height"] - rec["old_height"]
    return float("nan")


def _roof_changed(rec: dict, n_old: int, n_new: int) -> bool:
    """Roof types differ; only for 1:1 groups where both sides carry one."""
    if n_old != 1 or n_new != 1 or not rec["old_roof_type"] or not rec["new_roof_type"]:
        return False
    return rec["old_roof_type"].lower() != rec["new_roof_type"].lower()


def _old_only_record(oi: list[int], ctx: dict[str, Any]) -> dict[str, Any]:
    """Old building(s) without a new counterpart: demolished, not observed, or still standing."""
    p, u = ctx["params"], ctx["units"]
    old_u = shapely.union_all(ctx["old_polys"][oi])
    ev = evidence(old_u, ctx["ndsm"], u.height(p.min_height), ctx["vegetation"], ctx["density"])
    rec = _base(oi, [], ctx, old_u, None, ev)
    if ev["coverage"] < p.min_coverage:
        rec["class"] = "not_observed"
        rec["confidence"] = round(1.0 - ev["coverage"], 3)
    elif ev["support"] < p.min_support:
        rec["class"] = "demolished"
        strength = 1.0 - ev["support"] / p.min_support
        rec["confidence"] = _confidence(ev, 0.5 + 0.5 * strength, p, u)
    else:  # the nDSM shows something standing there that the new model lacks
        rec["class"] = "unchanged"
        rec["flags"] = "ndsm_only"
        rec["confidence"] = _confidence(ev, 0.5 * min(ev["support"], 1.0), p, u)
    return rec


def _new_only_record(ni: list[int], ctx: dict[str, Any]) -> dict[str, Any] | None:
    """New building(s) without an old counterpart; None when too small to report."""
    p, u = ctx["params"], ctx["units"]
    new_u = shapely.union_all([ctx["new"][j].footprint for j in ni])
    if new_u.area < u.area(p.min_new_area):
        return None
    ev = evidence(new_u, ctx["ndsm"], u.height(p.min_height), ctx["vegetation"], ctx["density"])
    rec = _base([], ni, ctx, new_u, None, ev)
    rec["class"] = "new"
    rec["confidence"] = _confidence(ev, min(ev["support"] / max(p.min_support, 1e-9), 1.0), p, u)
    return rec


# --------------------------------------------------------------------------- public API


def detect_changes(
    old: list,
    new: CityModel,
    ndsm: Raster,
    *,
    config: ChangeParams = ChangeParams(),
    units: Units | None = None,
    vegetation: Raster | None = None,
    density: Raster | None = None,
) -> ChangeResult:
    """Compare an old building database with a newly derived city model.

    Groups of linked old and new outlines are compared as wholes; where one new block
    covers several old buildings (a terrace the data cannot split), each old building
    is also compared on its own with the nDSM under it (height changes), and building
    evidence in the block outside every old outline is reported as new buildings.

    Parameters
    ----------
    old : list of Footprint-like
        Objects with ``id``, ``polygon`` (shapely, same CRS as ``new``) and
        ``attributes`` (dict; heights from the usual attribute names, see
        :data:`ROOF_Z_FIELDS`, :data:`HEIGHT_FIELDS`, :data:`AMBIGUOUS_HEIGHT_FIELDS`,
        or ``config.height_field``; roof type from ``roof_type``).
    new : CityModel
        Buildings of the run; those with status "failed" (no solid) are no evidence.
    ndsm : Raster
        nDSM of the run, (rows, cols) float32, NaN where there is no data.
    config : ChangeParams
    units : Units, optional
        Units of the CRS (thresholds are in metres); metres when None.
    vegetation : Raster, optional
        (rows, cols) on the nDSM grid, 1 where vegetation, 0 elsewhere, NaN no data.
    density : Raster, optional
        (rows, cols) point density in points per CRS unit2 on the nDSM grid.

    Returns
    -------
    ChangeResult

    Raises
    ------
    InputError
        The old database is empty or does not overlap the data at all.
    """
    units = units or Units()
    notes: list[str] = []
    warnings: list[str] = []
    old_ids, old_polys, old_attrs = _clean_old(old, notes)
    if not len(old_polys):
        raise InputError("old building database: no polygon with an area")
    _check_overlap(old_polys, new, ndsm)
    _note_overlaps(old_polys, notes)
    new_b = _new_buildings(new, notes)
    new_polys = np.array([b.footprint for b in new_b], dtype=object)
    groups = match_groups(old_polys, new_polys, config.overlap_share, units.length(config.shift))
    ctx = {
        "params": config,
        "units": units,
        "ndsm": ndsm,
        "vegetation": vegetation,
        "density": density,
        "old_ids": old_ids,
        "old_polys": old_polys,
        "old_attrs": old_attrs,
        "new": new_b,
    }
    measured, ground = _old_evidence(groups, ctx)
    ctx["measured"], ctx["ground"] = measured, ground
    ctx["old_roof"], ctx["old_height"] = _old_height_values(
        _old_heights(old_attrs, config, units), measured, ground, units, notes, warnings)
    in_blocks = _new_in_blocks(groups, ctx)
    ctx["carved"] = shapely.union_all([r["geometry"] for r in in_blocks]).buffer(
        units.length(config.shift), join_style="mitre") if in_blocks else None
    changes = []
    for oi, ni in groups:
        if oi and ni:
            rec = _group_record(oi, ni, ctx)
        elif oi:
            rec = _old_only_record(oi, ctx)
        else:
            rec = _new_only_record(ni, ctx)
        if rec is not None:
            changes.append(_tidy(rec))
        if len(oi) > 1 and ni:
            changes += [_tidy(r) for r in _block_height_records(oi, ni, ctx)]
    changes += [_tidy(r) for r in in_blocks]
    summary = {k: 0 for k in CHANGE_CODES}
    summary.update(Counter(r["class"] for r in changes))
    log.info("change detection: %s", ", ".join(f"{k} {v}" for k, v in summary.items() if v))
    return ChangeResult(changes, summary, notes, warnings)


def _old_evidence(groups, ctx) -> tuple[np.ndarray, np.ndarray]:
    """Per old building (n,): the nDSM height under it (90th percentile inside the
    outline shrunk by the shift) and the terrain height of the new buildings it is
    linked with (absolute, area-weighted), NaN where unknown."""
    p, u = ctx["params"], ctx["units"]
    polys = ctx["old_polys"]
    shrunk = _shrink(polys, u.length(p.shift))
    measured = np.full(len(polys), np.nan)
    ground = np.full(len(polys), np.nan)
    for i, geom in enumerate(shrunk):
        r, c, expected = _cells(geom, ctx["ndsm"])
        values = ctx["ndsm"].data[r, c]
        values = values[np.isfinite(values)]
        if len(values) >= max(p.min_coverage * expected, 1):
            measured[i] = float(np.percentile(values, 90))
    for oi, ni in groups:
        if oi and ni:
            new_b = [ctx["new"][j] for j in ni]
            ground[oi] = _weighted(np.array([b.ground_z for b in new_b]), np.array([b.footprint.area for b in new_b]))
    return measured, ground


def _old_height_values(heights: OldHeights, measured, ground, units: Units, notes: list, warnings: list):
    """(old_roof_z, old_height) arrays (n,) from the old heights and their reference;
    an ambiguous reference is decided by which one agrees with the data."""
    nan = np.full(len(heights.values), np.nan)
    if heights.field is None:
        warnings.append(
            "old building database has no height attribute (looked for "
            f"{', '.join(ROOF_Z_FIELDS[:3] + HEIGHT_FIELDS[:3] + AMBIGUOUS_HEIGHT_FIELDS[:1])}...): height changes not "
            "checked; name it with --old-height-field")
        return nan, nan
    v = heights.values
    reference = heights.reference
    ok = np.isfinite(v) & np.isfinite(measured) & np.isfinite(ground)
    off = {"ground": np.abs(v - measured)[ok], "absolute": np.abs(v - ground - measured)[ok]}
    if reference == "auto":
        if not ok.any():
            reference = "absolute"
            notes.append(f"old heights in {heights.field!r}: no building to tell their reference by; read as absolute")
        else:
            reference = min(off, key=lambda k: float(np.median(off[k])))
            other = "absolute" if reference == "ground" else "ground"
            notes.append(
                f"old heights in {heights.field!r} read as {'above ground' if reference == 'ground' else 'absolute'}: "
                f"median difference to the data {np.median(off[reference]) * units.vertical:.2f} m, "
                f"against {np.median(off[other]) * units.vertical:.2f} m the other way")
    else:
        notes.append(f"old heights in {heights.field!r}, {'above ground' if reference == 'ground' else 'absolute'}")
    if ok.sum() >= 3 and np.median(off[reference]) > units.height(5.0):
        warnings.append(
            f"old heights in {heights.field!r} differ from the data by a median "
            f"{np.median(off[reference]) * units.vertical:.1f} m: check --old-height-reference and their unit")
    return (v, nan) if reference == "absolute" else (nan, v)


def _block_height_records(oi: list[int], ni: list[int], ctx: dict[str, Any]) -> list[dict[str, Any]]:
    """Height changes of old buildings that share one new block, each judged on the
    nDSM under its own outline (flag ``in_block``)."""
    p, u = ctx["params"], ctx["units"]
    out = []
    block_ids = [ctx["new"][j].id for j in ni]
    for i in oi:
        old_rel = ctx["old_height"][i]
        if not np.isfinite(old_rel):
            old_rel = ctx["old_roof"][i] - ctx["ground"][i]
        dh = ctx["measured"][i] - old_rel
        if not (np.isfinite(dh) and abs(dh) > u.height(p.height_threshold)):
            continue
        geom = ctx["old_polys"][i]
        ev = evidence(geom, ctx["ndsm"], u.height(p.min_height), ctx["vegetation"], ctx["density"])
        rec = _base([i], [], ctx, geom, None, ev)
        rec.update({"class": "height_changed", "flags": "height_changed,in_block", "block_new_ids": block_ids,
                    "dh": dh * u.vertical, "new_height": ctx["measured"][i]})
        rec["confidence"] = _confidence(ev, _margin(dh, u.height(p.height_threshold), True), p, u)
        out.append(rec)
    return out


def _new_in_blocks(groups, ctx: dict[str, Any]) -> list[dict[str, Any]]:
    """New buildings inside blocks (new buildings linked with several old ones): building evidence (new outlines, nDSM at
    least ``block_new_height``, no vegetation) outside every old outline grown by the
    shift, opened by three cells, each region then given back the strip along the old
    outlines (within the new outlines) and kept from ``block_new_area`` on. A region
    touching one old building only and smaller than ``extension_share`` of it is that
    building's extension instead (left to its group's footprint comparison); so is
    any growth of an old building that stands alone."""
    import rasterio.features
    from scipy import ndimage

    p, u = ctx["params"], ctx["units"]
    ndsm = ctx["ndsm"]
    # blocks: new buildings linked with several old ones (beside one old building alone, growth is its extension)
    matched = [ctx["new"][j].footprint for oi, ni in groups if len(oi) > 1 and ni for j in ni]
    if not matched:
        return []
    shift = u.length(p.shift)
    old_grown = shapely.buffer(ctx["old_polys"], shift, join_style="mitre")

    def burn(geoms) -> np.ndarray:
        return rasterio.features.rasterize([(g, 1) for g in geoms], out_shape=ndsm.shape, transform=ndsm.transform,
                                           fill=0, dtype="uint8").astype(bool)

    mask = burn(matched) & ~burn(old_grown) & (np.nan_to_num(ndsm.data, nan=-np.inf) >= u.height(p.block_new_height))
    if ctx["vegetation"] is not None:
        mask &= ~(np.nan_to_num(ctx["vegetation"].data) > 0.5)
    mask = ndimage.binary_opening(mask, structure=np.ones((3, 3), bool))  # no strips a cell wide
    labels, n = ndimage.label(mask)
    if not n:
        return []
    # each region given back the strip along the old outlines it was kept off, inside the new outlines
    within = shapely.difference(shapely.union_all(matched), shapely.union_all(ctx["old_polys"]))
    tree = shapely.STRtree(ctx["old_polys"])
    out = []
    pieces: dict[int, list] = {}
    for g, k in rasterio.features.shapes(labels.astype(np.int32), mask=labels > 0, transform=ndsm.transform):
        pieces.setdefault(int(k), []).append(shapely.geometry.shape(g))
    for k in range(1, n + 1):
        region = shapely.union_all(pieces[k])
        region = shapely.intersection(region.buffer(shift + ndsm.resolution, join_style="mitre"), within)
        region = max(shapely.get_parts(region), key=lambda g: g.area, default=region)
        if region.area < u.area(p.block_new_area):
            continue
        touched = tree.query(region, predicate="dwithin", distance=ndsm.resolution)
        if len(touched) == 1 and region.area < p.extension_share * ctx["old_polys"][touched[0]].area:
            continue  # beside one old building only, and smaller than a house: its extension
        ev = evidence(region, ndsm, u.height(p.min_height), ctx["vegetation"], ctx["density"])
        rec = _base([], [], ctx, region, None, ev)
        inside = [b.id for b in ctx["new"] if b.footprint.intersects(region)]
        rec.update({"class": "new", "flags": "in_block", "block_new_ids": inside,
                    "new_area": _m2(region.area, u), "new_height": ev["ndsm_height"]})
        rec["confidence"] = _confidence(ev, min(ev["support"] / max(p.min_support, 1e-9), 1.0), p, u)
        out.append(rec)
    return out


def _tidy(rec: dict) -> dict:
    """NaN to None and rounded floats, so records go straight to JSON / GeoJSON."""
    for k, v in rec.items():
        if isinstance(v, float):
            rec[k] = None if not np.isfinite(v) else round(v, 3)
    return rec


def _check_overlap(old_polys: np.ndarray, new: CityModel, ndsm: Raster) -> None:
    """Raise InputError when no old outline touches the data's extent."""
    if not np.isfinite(ndsm.data).any():
        raise InputError("change detection: the nDSM has no data, nothing to compare with")
    if shapely.intersects(old_polys, shapely.box(*ndsm.bounds)).any():
        return
    ob = shapely.total_bounds(old_polys)
    raise InputError(
        "old building database does not overlap the data: its extent "
        f"({ob[0]:.1f}, {ob[1]:.1f}, {ob[2]:.1f}, {ob[3]:.1f}) is outside the nDSM extent "
        f"{tuple(round(v, 1) for v in ndsm.bounds)}; check that both use the same CRS"
    )


def _note_overlaps(old_polys: np.ndarray, notes: list[str]) -> None:
    """Note old outlines overlapping each other (they are compared as one group)."""
    tree = shapely.STRtree(old_polys)
    a, b = tree.query(old_polys, predicate="intersects")
    keep = a < b
    a, b = a[keep], b[keep]
    if len(a):
        inter = shapely.area(shapely.intersection(old_polys[a], old_polys[b]))
        smaller = np.minimum(shapely.area(old_polys[a]), shapely.area(old_polys[b]))
        n = int((inter > 0.01 * smaller).sum())
        if n:
            notes.append(
                f"{n} pairs of old buildings overlap each other; they are compared together"
            )


def change_features(
    result: ChangeResult, *, changed_only: bool = False
) -> tuple[list, list[dict[str, Any]]]:
    """Geometries and properties for :func:`recon3d.io.vectors.write_features`.

    Parameters
    ----------
    result : ChangeResult
    changed_only : bool
        Leave out "unchanged" and "not_observed" records.

    Returns
    -------
    geometries : list of shapely geometries, one per record
    properties : list of dict
        Plain values only (id lists joined with commas), plus ``code`` (:data:`CHANGE_CODES`).
    """
    geoms, props = [], []
    for rec in result.changes:
        if changed_only and rec["class"] in ("unchanged", "not_observed"):
            continue
        geoms.append(rec["geometry"])
        p = {k: ",".join(v) if isinstance(v, list) else v for k, v in rec.items() if k != "geometry"}
        p["code"] = CHANGE_CODES[rec["class"]]
        props.append(p)
    return geoms, props


def change_raster(result: ChangeResult, grid: Raster) -> Raster:
    """The change class of every cell of ``grid`` (codes of :data:`CHANGE_CODES`).

    Returns
    -------
    Raster
        (rows, cols) float32: the class code where a record's geometry covers the
        cell centre, NaN elsewhere. Changes are drawn after unchanged records, so a
        change wins where outlines overlap.
    """
    data = np.full(grid.shape, np.nan, dtype=np.float32)
    order = sorted(
        result.changes, key=lambda r: (r["class"] != "not_observed", r["class"] != "unchanged")
    )
    for rec in order:
        r, c, _ = _cells(rec["geometry"], grid)
        data[r, c] = CHANGE_CODES[rec["class"]]
    legend = ", ".join(f"{v} {k}" for k, v in CHANGE_CODES.items())
    return grid.like(data, product="change", codes=legend)


def updated_model(old: list, new_city: CityModel, result: ChangeResult) -> CityModel:
    """The old database brought up to date with the new model.

    * unchanged 1:1: the new building (geometry, heights, solids) under the old id;
    * unchanged splits / merges and every change: the new buildings, 1:1 changes
      under the old id, others under their new id (prefixed ``new-`` if it clashes
      with an old id);
    * new: the new building; demolished: dropped;
    * not observed: the old outline kept as it was (status "failed", reason
      "not_observed"), heights from its attributes when present.

    Every building carries ``change`` (class), ``change_confidence`` and
    ``lineage_old_ids`` (comma-separated old ids) attributes.
    """
    by_id = {b.id: b for b in new_city.buildings}
    old_by_id = {str(o.id): o for o in old}
    old_ids = set(old_by_id)
    out: list[Building] = []
    for rec in result.changes:
        cls = rec["class"]
        lineage = {
            "change": cls,
            "change_confidence": rec["confidence"],
            "lineage_old_ids": ",".join(rec["old_ids"]),
        }
        if cls == "demolished" or "in_block" in rec["flags"]:  # the block's own record writes it
            continue
        if not rec["new_ids"]:  # not observed, or standing in the nDSM without a new building
            for i in rec["old_ids"]:
                out.append(_old_building(old_by_id.get(i.split("#")[0]), i, lineage))
            continue
        keep_old_id = len(rec["old_ids"]) == 1 and len(rec["new_ids"]) == 1
        for nid in rec["new_ids"]:
            b = by_id[nid]
            bid = rec["old_ids"][0] if keep_old_id else (f"new-{nid}" if nid in old_ids else nid)
            out.append(_copy(b, bid, lineage))
    metadata = dict(new_city.metadata, change_summary=dict(result.summary))
    return CityModel(out, new_city.crs, new_city.frame, metadata)


def _copy(b: Building, bid: str, extra: dict) -> Building:
    attrs = {**b.attributes, **extra}
    solids = dict(b.solids)
    return Building(bid, b.footprint, b.ground_z, b.roof_z, solids, b.status, b.reason, attrs)


def _old_building(item, fid: str, extra: dict) -> Building:
    attrs = dict(getattr(item, "attributes", {}) or {}) if item is not None else {}
    low = {str(k).lower(): v for k, v in attrs.items()}
    roof = _first_number(low, ROOF_Z_FIELDS)
    ground = _first_number(low, ("ground_z",))
    reason = "not_observed" if extra["change"] == "not_observed" else "not_modelled"
    poly = item.polygon if item is not None else shapely.Polygon()
    return Building(fid, poly, ground, roof, {}, "failed", reason, {**attrs, **extra})
