"""Coordinate reference systems, units and the local frame meshes live in.

recon3d keeps every product in the CRS of its input. Parameters that are physical
lengths (a 2.5 m minimal building height, a 25 m2 minimal area) are converted into
the CRS units with :class:`Units`, so a cloud in US survey feet (Autzen) gives the
same buildings as the same cloud in metres.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pyproj
from pyproj.exceptions import CRSError as _ProjCRSError

from recon3d.errors import CRSError

__all__ = [
    "CRSIdentification",
    "LocalFrame",
    "Units",
    "crs_authority",
    "crs_code",
    "crs_name",
    "crs_units",
    "identify_crs",
    "parse_crs",
    "to_rasterio_crs",
    "uncoded_wkt",
]


def parse_crs(text: str | int | pyproj.CRS, *, source: str = "--crs") -> pyproj.CRS:
    """Parse a user CRS ("EPSG:7415", 2154, WKT, PROJ string) into a :class:`pyproj.CRS`.

    Raises
    ------
    CRSError
        When PROJ does not know the CRS; the message names ``source``.
    """
    if isinstance(text, pyproj.CRS):
        return text
    try:
        return pyproj.CRS.from_user_input(text)
    except _ProjCRSError as exc:
        raise CRSError(f"{source}: unknown coordinate reference system {text!r}") from exc


@functools.lru_cache(maxsize=64)
def crs_authority(crs: pyproj.CRS, min_confidence: int = 70) -> tuple[str, str] | None:
    """(authority, code) of a CRS, e.g. ("EPSG", "7415"), or None.

    Cached: for a CRS given as bare WKT, PROJ searches its whole database (~0.1 s).
    """
    return crs.to_authority(min_confidence=min_confidence)


def crs_code(crs: pyproj.CRS | None) -> str | None:
    """The code a CRS goes by: "EPSG:7415", "EPSG:2994+6360" for a compound CRS whose
    horizontal and vertical parts have codes but the whole has none, else None."""
    if crs is None:
        return None
    auth = crs_authority(crs)
    if auth:
        return f"{auth[0]}:{auth[1]}"
    parts = [crs_authority(c) for c in crs.sub_crs_list] if crs.is_compound else []
    if len(parts) == 2 and all(parts) and parts[0][0] == parts[1][0]:
        return f"{parts[0][0]}:{parts[0][1]}+{parts[1][1]}"
    return None


def crs_name(crs: pyproj.CRS | None) -> str:
    """Short human name of a CRS: its code (:func:`crs_code`) where it has one, else its name."""
    if crs is None:
        return "none"
    return crs_code(crs) or crs.name


def uncoded_wkt(crs: pyproj.CRS | None) -> str | None:
    """The one-line WKT of a CRS that has no code (:func:`crs_code`), for the files that
    otherwise name a CRS by its code only (OBJ header, glTF extras); None when it has one."""
    if crs is None or crs_code(crs):
        return None
    return crs.to_wkt()


#: Least confidence (PROJ's, 0-100) at which an EPSG code found for a CRS is taken.
#: PROJ gives 100 to a CRS that carries the code or matches it name for name, 70 to
#: one equivalent to it under other names (an ESRI WKT), 25 or less to a near miss.
IDENTIFY_MIN_CONFIDENCE = 70


@dataclass(frozen=True)
class CRSIdentification:
    """The EPSG code found for the CRS of an input, and how sure PROJ is of it.

    Attributes
    ----------
    crs : pyproj.CRS
        The CRS the products are written in: the EPSG definition when a code was
        found (the same CRS, so every format can name it), else the input's own.
    given : str
        The name the input gave its CRS.
    code : str or None
        "EPSG:2994", or "EPSG:2994+6360" for a compound CRS identified part by part.
    confidence : int or None
        PROJ's confidence in the code (for parts identified apart, the lower one).
    how : str
        How the code was found, or why none was.
    best_guess : str or None
        Without a code: PROJ's best candidate and its confidence, which is too low or
        not the same CRS ("EPSG:2992 at 25 %").
    """

    crs: pyproj.CRS
    given: str
    code: str | None
    confidence: int | None
    how: str
    best_guess: str | None = None

    def record(self) -> dict:
        """The identification as run.json keeps it."""
        return {
            "given": self.given,
            "epsg": self.code,
            "confidence": self.confidence,
            "how": self.how,
            "best_guess": self.best_guess,
            "written_as": "EPSG code (and its WKT)" if self.code else "WKT only",
        }

    def warnings(self) -> list[str]:
        """What the user must know about the products' CRS (none when it has one EPSG code)."""
        if self.code is None:
            guess = f" (best candidate {self.best_guess})" if self.best_guess else ""
            return [
                f"the CRS {self.given!r} has no EPSG code PROJ can identify{guess}: the rasters, cloud.laz, "
                "footprints.gpkg, buildings.glb and buildings.obj carry it as WKT; buildings.city.json "
                "(referenceSystem) and footprints.geojson cannot name it"
            ]
        if "+" in self.code:
            horizontal, vertical = self.code.split("+")
            return [
                f"the CRS {self.given!r} is {self.code} (no single EPSG code): buildings.city.json names "
                f"the horizontal {horizontal} only (CityJSON 2.0 has one referenceSystem); heights are in "
                f"EPSG:{vertical}"
            ]
        return []


@functools.lru_cache(maxsize=32)
def identify_crs(crs: pyproj.CRS, min_confidence: int = IDENTIFY_MIN_CONFIDENCE) -> CRSIdentification:
    """The EPSG code of a CRS described by WKT (ESRI's or OGC's), when PROJ finds one.

    A code counts only with PROJ's confidence at least ``min_confidence`` and when its
    definition is the same CRS (:meth:`pyproj.CRS.equals`, axis order aside): the
    products are then written in the EPSG definition. A compound CRS without a code
    of its own is identified part by part (horizontal + vertical).

    Parameters
    ----------
    crs : pyproj.CRS
    min_confidence : int

    Returns
    -------
    CRSIdentification
    """
    found = _epsg_match(crs, min_confidence)
    if found:
        code, confidence, how = found
        return CRSIdentification(pyproj.CRS.from_epsg(code), crs.name, f"EPSG:{code}", confidence, how)
    parts = [_epsg_match(c, min_confidence) for c in crs.sub_crs_list] if crs.is_compound else []
    if len(parts) == 2 and all(parts):
        code = f"EPSG:{parts[0][0]}+{parts[1][0]}"
        how = f"no EPSG code for the pair; horizontal and vertical parts matched apart ({parts[0][2]})"
        return CRSIdentification(pyproj.CRS.from_user_input(code), crs.name, code, min(p[1] for p in parts), how)
    return CRSIdentification(crs, crs.name, None, None, "PROJ finds no EPSG CRS equivalent to it",
                             _best_guess(crs))


def _readings(crs: pyproj.CRS):
    """The CRS as given, then re-read with its names taken as ESRI's: a WKT1 naming its
    datum the ESRI way ("NAD83_High_Accuracy_Regional_Network") matches no EPSG datum
    until PROJ's ESRI aliases map it."""
    yield "matched by PROJ as given", crs
    try:
        esri = crs.to_wkt("WKT1_ESRI")
    except _ProjCRSError:
        return
    if esri:
        try:
            yield "matched by PROJ with its names read as ESRI's", pyproj.CRS.from_wkt(esri)
        except _ProjCRSError:
            return


def _epsg_match(crs: pyproj.CRS, min_confidence: int) -> tuple[int, int, str] | None:
    """(code, confidence, how) of the first EPSG CRS PROJ matches to ``crs`` and that
    is the same CRS, or None.

    A WKT1 with ``TOWGS84`` (a bound CRS) is matched by the CRS it binds: its datum shift
    to WGS84 is then PROJ's own for the code.
    """
    if crs.is_bound:
        found = _epsg_match(crs.source_crs, min_confidence)
        return (found[0], found[1], f"{found[2]}, its TOWGS84 left to PROJ's database") if found else None
    for how, reading in _readings(crs):
        for match in reading.list_authority(auth_name="EPSG", min_confidence=min_confidence):
            try:
                candidate = pyproj.CRS.from_epsg(int(match.code))
            except (_ProjCRSError, ValueError):
                continue
            if candidate.equals(crs, ignore_axis_order=True):
                return int(match.code), int(match.confidence), how
    return None


def _best_guess(crs: pyproj.CRS) -> str | None:
    """PROJ's best EPSG candidate for ``crs`` at any confidence ("EPSG:2992 at 25 %"), or None."""
    for _, reading in _readings(crs.source_crs if crs.is_bound else crs):
        matches = reading.list_authority(auth_name="EPSG", min_confidence=1)
        if matches:
            return f"EPSG:{matches[0].code} at {matches[0].confidence} %"
    return None


#: Degrees the data may reach beyond its CRS's published area of use.
AREA_OF_USE_MARGIN = 2.0


def check_area_of_use(crs: pyproj.CRS, lo, hi, *, source: str) -> None:
    """Refuse data whose extent lies wholly outside its CRS's area of use.

    A file labelled with the wrong CRS (Dutch RD coordinates declared as French Lambert
    93) otherwise reads, reprojects and lands hundreds of kilometres away.

    Parameters
    ----------
    crs : pyproj.CRS
    lo, hi : sequence of float
        Lowest and highest corner (x, y) of the data in ``crs``.
    source : str
        The file, for the message.

    Raises
    ------
    CRSError
        When none of the extent's corners and centre falls in the area of use widened
        by :data:`AREA_OF_USE_MARGIN` degrees.
    """
    from recon3d.errors import CRSError

    area = crs.area_of_use
    if area is None:
        return
    xs = np.array([lo[0], hi[0], lo[0], hi[0], 0.5 * (lo[0] + hi[0])], float)
    ys = np.array([lo[1], lo[1], hi[1], hi[1], 0.5 * (lo[1] + hi[1])], float)
    try:
        lon, lat = _to_lonlat(crs).transform(xs, ys)
    except pyproj.exceptions.ProjError:
        lon = lat = np.full(5, np.nan)
    m = AREA_OF_USE_MARGIN
    inside = (lon >= area.west - m) & (lon <= area.east + m) & (lat >= area.south - m) & (lat <= area.north + m)
    if not np.any(inside):
        where = "no position on Earth" if not np.isfinite(lon).any() else f"lon {np.nanmean(lon):.2f}, lat {np.nanmean(lat):.2f}"
        raise CRSError(
            f"{source}: its coordinates, read in {crs_name(crs)}, lie at {where}, outside that CRS's area of use "
            f"({area.name}); is the CRS right?"
        )


@functools.lru_cache(maxsize=16)
def _to_lonlat(crs: pyproj.CRS) -> pyproj.Transformer:
    """A transformer to longitude and latitude, made once per CRS: making one costs
    about 25 ms, and a survey of a few hundred tiles checks every tile's extent."""
    return pyproj.Transformer.from_crs(crs, 4326, always_xy=True)


def to_rasterio_crs(crs: pyproj.CRS | None):
    """The same CRS as a :class:`rasterio.crs.CRS` (for GeoTIFF writing)."""
    if crs is None:
        return None
    from rasterio.crs import CRS as RioCRS

    auth = crs_authority(crs, 100)
    if auth and auth[0] == "EPSG":
        return RioCRS.from_epsg(int(auth[1]))
    return RioCRS.from_wkt(crs.to_wkt())


@dataclass(frozen=True)
class Units:
    """Linear units of a CRS, as metres per CRS unit.

    Attributes
    ----------
    horizontal : float
        Metres per horizontal unit (1.0 for metres, 0.3048006 for US survey feet).
    vertical : float
        Metres per height unit. Taken from the vertical part of a compound CRS; a
        projected CRS without a vertical part is assumed to use its horizontal unit
        for heights too (how LAS files in feet are written).
    name : str
        Name of the horizontal unit, for messages and run.json.
    vertical_source : str
        Where the vertical unit came from ("compound CRS" or "assumed horizontal").
    """

    horizontal: float = 1.0
    vertical: float = 1.0
    name: str = "metre"
    vertical_source: str = "assumed horizontal"

    def length(self, metres: float) -> float:
        """A horizontal length in metres expressed in CRS units."""
        return metres / self.horizontal

    def area(self, square_metres: float) -> float:
        """An area in m2 expressed in squared CRS units."""
        return square_metres / self.horizontal**2

    def height(self, metres: float) -> float:
        """A height difference in metres expressed in CRS height units."""
        return metres / self.vertical


def crs_units(crs: pyproj.CRS, *, source: str = "input") -> Units:
    """Units of a projected (optionally compound) CRS.

    Raises
    ------
    CRSError
        For a geographic CRS (degrees cannot be gridded in metres).
    """
    horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
    if not horizontal.is_projected:
        raise CRSError(
            f"{source}: CRS {crs_name(crs)} is not projected (units are degrees); "
            "reproject the data to a projected CRS such as UTM"
        )
    axis = horizontal.axis_info[0]
    h = float(axis.unit_conversion_factor)
    if crs.is_compound and len(crs.sub_crs_list) > 1 and crs.sub_crs_list[1].axis_info:
        v = float(crs.sub_crs_list[1].axis_info[0].unit_conversion_factor)
        vsource = "compound CRS"
    else:
        v, vsource = h, "assumed horizontal"
    return Units(horizontal=h, vertical=v, name=axis.unit_name, vertical_source=vsource)


@dataclass(frozen=True)
class LocalFrame:
    """A translated copy of the world CRS, so float32 meshes keep millimetres.

    manifold3d and glTF store float32 (7 significant digits); national-grid
    coordinates such as (85000, 447500) or UTM northings lose centimetres there.
    Meshes are built in local coordinates ``world - origin`` and the origin is added
    back at export (CityJSON ``transform``, glTF root translation).

    Parameters
    ----------
    origin : (3,) float
        World coordinates of the local origin.
    """

    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def around(cls, xyz_min, step: float = 100.0) -> LocalFrame:
        """A frame whose origin is ``xyz_min`` snapped down to a multiple of ``step``."""
        o = np.floor(np.asarray(xyz_min, dtype=np.float64) / step) * step
        return cls(origin=(float(o[0]), float(o[1]), float(o[2])))

    def to_local(self, xyz: np.ndarray) -> np.ndarray:
        """(n, 3) world coordinates to (n, 3) local coordinates."""
        return np.asarray(xyz, dtype=np.float64) - np.asarray(self.origin)

    def to_world(self, xyz: np.ndarray) -> np.ndarray:
        """(n, 3) local coordinates to (n, 3) world coordinates."""
        return np.asarray(xyz, dtype=np.float64) + np.asarray(self.origin)
