"""Pipeline configuration: one frozen dataclass per stage.

A value of ``None`` means "choose from the data"; the pipeline records the value it
chose and why in run.json. Configurations come from a TOML file (``--config``) whose
tables are named after the stages, and from dotted overrides (``--set dsm.resolution=0.5``).

Examples
--------
>>> cfg = PipelineConfig().with_overrides(["dsm.resolution=0.5", "ground.method='provider'"])
>>> cfg.dsm.resolution, cfg.ground.method
(0.5, 'provider')
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from recon3d.errors import InputError

__all__ = [
    "BuildingsConfig",
    "ChangeConfig",
    "DsmConfig",
    "DtmConfig",
    "GroundConfig",
    "LodConfig",
    "OrthoConfig",
    "PipelineConfig",
    "StereoConfig",
    "TilesConfig",
]


@dataclass(frozen=True)
class StereoConfig:
    """Dense matching of stereo pairs (frame and satellite).

    Attributes
    ----------
    max_disparities : int
        Widest disparity search per pair; the range itself comes from the sparse points.
    engine : str
        Dense matching engine: "census" (census cost and recon3d's SGM, the most
        accurate) or "sgbm" (OpenCV's StereoSGBM, faster).
    min_angle : float
        Smallest ray intersection angle (degrees) for a triangulated point.
    max_parallax : float
        Largest residual vertical parallax (px) accepted after rectification.
    tile_size : int or None
        Satellite pairs: largest tile (px of the reference image, at least 128) rectified
        with its own local affine camera approximation; None: one tile up to 1024 px,
        800 px tiles beyond.
    vectors : bool
        Frame stereo: bound the matching by what the user gave (``--dem``, spot heights
        and breaklines, footprints with roof heights), see :mod:`recon3d.stereo.constraints`.
    dem_tolerance : float
        Metres the surface may lie below the ``--dem``.
    roof_tolerance : float
        Metres of slack around the footprints' roof heights and inside their outlines.
    footprint_weight : float
        How firmly roof heights bound the matching, 0 (not at all) to 1 (never crossed).
    max_object_height : float or None
        Metres the tallest object stands above the ``--dem``; None: measured on the
        sparse points (their highest above the DEM, plus 10 m).
    max_partners : int
        Frame blocks: each image is matched with its best this many partners (overlap,
        base); 0 matches every usable pair.
    slant : float or None
        Census engine, frame pairs: disparity gradient (px per px) of the sheared census
        windows matched besides the upright ones (see ``MatchParams.slant``), 0 for
        upright windows only; None: 0.5 for pairs whose base-to-height ratio is
        ``SLANT_BASE_TO_HEIGHT`` or more (a 45 degree roof face then changes disparity by
        half a pixel per pixel or more), else 0.
    sharpen_steps : float
        Frame pairs: 0 (off, the default) or the ratio of
        ``recon3d.stereo.match.sharpen_steps``: a pixel beside a disparity step that took
        the raised side goes to the lower side when its own colours match the right
        image there within this factor of how well they match at its own disparity (the
        census window carries a roof a pixel or two onto the street). 1.2 lowered the
        tolerant DSM RMS on 22 of 25 rendered surveys at 1000 px (3 x 3 rays per pixel;
        strip_of_3 0.51 -> 0.42 m), but at 400 px rendered with one ray per pixel, where a
        pixel is 0.5 m, it took a pixel off every roof edge (nadir_pair footprint
        completeness 99.8 -> 94.2 %; with 3 x 3 rays, as a sensor integrates, 99.8 %).
    tie_point_margin : float
        Frame stereo: a dense point more than this many metres below every tie point
        (sparse point) around it, or, with no tie point around it, this much plus three
        spreads below the plane under the tie points, is a mismatch and is removed
        (``recon3d.stereo.check.under_tie_points``); ``inf`` turns the test off.
    """

    max_disparities: int = 384
    engine: str = "census"
    min_angle: float = 1.0
    max_parallax: float = 1.0
    tile_size: int | None = None
    vectors: bool = True
    dem_tolerance: float = 2.0
    roof_tolerance: float = 1.0
    footprint_weight: float = 0.5
    max_object_height: float | None = None
    max_partners: int = 4
    slant: float | None = None
    sharpen_steps: float = 0.0
    tie_point_margin: float = 10.0

    def __post_init__(self) -> None:
        if self.engine not in ("census", "sgbm"):
            raise InputError(f"stereo.engine {self.engine!r}: \"census\" or \"sgbm\"")
        if self.max_disparities < 16:
            raise InputError(f"stereo.max_disparities {self.max_disparities}: at least 16")
        if self.dem_tolerance < 0 or self.roof_tolerance < 0:
            raise InputError("stereo.dem_tolerance and stereo.roof_tolerance must be >= 0")
        if not 0.0 <= self.footprint_weight <= 1.0:
            raise InputError(f"stereo.footprint_weight {self.footprint_weight}: between 0 and 1")
        if self.max_partners < 0:
            raise InputError(f"stereo.max_partners {self.max_partners}: at least 0 (0: every usable pair)")
        if self.max_object_height is not None and self.max_object_height <= 0:
            raise InputError(f"stereo.max_object_height {self.max_object_height}: must be > 0")
        if self.slant is not None and not 0.0 <= self.slant < 1.0:
            raise InputError(f"stereo.slant {self.slant}: from 0 (off) to below 1 px per px, or unset for automatic")
        if self.sharpen_steps < 0:
            raise InputError(f"stereo.sharpen_steps {self.sharpen_steps}: 0 (off) or a ratio > 0")
        if self.tile_size is not None and self.tile_size < 128:
            raise InputError(f"stereo.tile_size {self.tile_size}: at least 128 px (or unset for automatic)")


@dataclass(frozen=True)
class DsmConfig:
    """Gridding of the point cloud into the DSM.

    Attributes
    ----------
    resolution : float or None
        Cell size in metres; None picks about twice the mean point spacing.
    max_hole_area : float or None
        Holes up to this area (m2) are filled from their neighbours; larger ones
        (water) stay NaN. None: 25 m2 for LiDAR, 200 m2 for satellite stereo and
        1000 m2 for frame stereo, inside the area both images see (ground hidden from
        one image behind buildings; a wide-base survey hides whole streets).
    """

    resolution: float | None = None
    max_hole_area: float | None = None

    def __post_init__(self) -> None:
        if self.resolution is not None and not (0.01 <= self.resolution <= 1000.0):
            raise InputError(f"dsm.resolution {self.resolution}: between 0.01 and 1000 (metres), or unset for automatic")
        if self.max_hole_area is not None and not (0.0 <= self.max_hole_area <= 1e8):
            raise InputError(f"dsm.max_hole_area {self.max_hole_area}: between 0 and 1e8 (m2), or unset for automatic")


@dataclass(frozen=True)
class GroundConfig:
    """Ground filtering (progressive morphological filter, SMRF style).

    Attributes
    ----------
    method : {"auto", "smrf", "tophat", "drape", "provider"}
        "auto" picks "smrf" for LiDAR and for clouds without return numbers (stereo)
        whose surface noise is under 0.2 m, "tophat" for noisier ones; "provider"
        trusts the input's class 2. See ``recon3d.terrain.ground``.
    cell : float or None
        Cell of the minimum surface in metres; None uses 1 m, or the DSM cell if coarser.
    max_window : float or None
        Largest opening window in metres; None takes it from the largest building
        blob seen in the data (bounded to 10..60 m).
    slope : float or None
        Terrain slope (rise over run) the filter tolerates; None measures it.
    threshold : float or None
        Height above the provisional terrain (m) below which a point is ground; None
        uses 0.5 m, or three times the measured noise when that is larger.
    scalar : float
        Extra tolerance per unit of local slope times cell size (SMRF's "scalar").
    """

    method: str = "auto"
    cell: float | None = None
    max_window: float | None = None
    slope: float | None = None
    threshold: float | None = None
    scalar: float = 1.25

    def __post_init__(self) -> None:
        methods = ("auto", "smrf", "tophat", "drape", "provider")
        if self.method not in methods:
            raise InputError(f"ground.method must be one of {', '.join(methods)}; not {self.method!r}")


@dataclass(frozen=True)
class DtmConfig:
    """Interpolation of the ground points into the DTM (Delaunay triangulation)."""

    method: str = "delaunay"


@dataclass(frozen=True)
class BuildingsConfig:
    """Building detection and LoD1 heights (classic photogrammetric capture rules).

    Attributes
    ----------
    min_height : float
        nDSM height (m) above which a cell can belong to a building.
    min_area : float
        Smallest building footprint kept (m2); also the smallest courtyard kept.
    roof_percentile : float
        Percentile of the heights inside a footprint used as the LoD1 roof.
    footprint_shift : float
        Largest map-to-data shift (m) tolerated for given footprints.
    split_height : float
        Height jump (m) between neighbouring cells that separates two buildings of one
        block (and a superstructure from its roof when it covers ``min_area``); 0 keeps
        connected blocks whole.
    split_step : float
        Height step (m) between neighbouring roof cells, not explained by the roof's
        slope, that marks a party wall: a block is cut along lines of such steps crossing
        it from wall to wall when the pieces are buildings (``min_area``, at least
        ``min_split_width`` wide, not an annex enclosed by the rest; see
        :func:`recon3d.buildings.detect.split_at_steps`); 0 switches it off, and so
        does a ``split_height`` of 0.
    min_split_width : float
        Narrowest piece (m) cut off a block at a step; narrower ones (annexes, lean-tos,
        the fringe of a wall) stay attached.
    grow_height : float
        Lower roofs attached to a building (annexes, lean-tos) at least this high (m)
        join it; equal to ``min_height`` to switch off.
    min_width : float
        Raised structures narrower than this (m) are not buildings (walls, hedges,
        wires); the building mask is opened with a square of this size.
    vegetation_min_height : float
        Points at least this high (m) above the terrain are tested for vegetation.
    vegetation_roughness : float
        RMS (m) of a point's neighbours about their best plane above which, with a
        multi-return echo or a green colour, the point is vegetation.
    vegetation_neighbours : int
        Neighbours of a point for its covariance features and its majority vote.
    roof_roughness : float
        RMS (m) of the DSM about a 3 x 3 cell plane below which a cell counts as smooth.
    min_smooth_share : float
        Share of smooth cells a blob needs to be a building (tree crowns are rough).
    min_edge : float
        Shortest edge (m) of a regularised outline.
    regularize : bool
        Regularise detected outlines (dominant directions, straight edges); False keeps
        the Douglas-Peucker outlines.
    image_outlines : bool
        Frame stereo: move each detected outline's edges to the eaves where the two most
        nadir images agree (:mod:`recon3d.buildings.image_outline`); False keeps the nDSM
        outlines.
    """

    min_height: float = 2.5
    min_area: float = 25.0
    roof_percentile: float = 90.0
    footprint_shift: float = 1.0
    split_height: float = 2.0
    split_step: float = 0.3
    min_split_width: float = 4.5
    grow_height: float = 2.0
    min_width: float = 1.5
    vegetation_min_height: float = 1.0
    vegetation_roughness: float = 0.05
    vegetation_neighbours: int = 10
    roof_roughness: float = 0.15
    min_smooth_share: float = 0.5
    min_edge: float = 0.75
    regularize: bool = True
    image_outlines: bool = True


@dataclass(frozen=True)
class LodConfig:
    """Which levels of detail are built, and how roofs are segmented (LoD1.3, LoD2.2).

    Lengths are in metres and areas in m2 (converted to the CRS units by the
    pipeline). See ``recon3d.buildings.roofs`` and ``recon3d.buildings.lod``.

    Attributes
    ----------
    lods : tuple of str
        Levels of detail to build among "1", "1.3" and "2.2". A "2.2" that cannot be
        built falls back to "1.3", then "1", with a reason code.
    plane_distance : float
        Largest point-to-plane distance (m) of a roof plane's inliers (RANSAC threshold).
    min_plane_area : float
        Smallest roof plane kept (m2, plan view); with the point density it gives the
        minimal number of points of a plane (never fewer than ``min_plane_points``).
    min_plane_points : int
        Fewest points of a roof plane.
    max_planes : int
        A roof needing more planes than this is "too_many_planes" (falls back to LoD1.3).
    max_roof_rms : float
        A LoD2.2 roof whose robust point-to-roof RMS (m) exceeds this falls back ("poor_fit").
    lod13_step : float
        Height difference (m) below which neighbouring LoD1.3 blocks are merged.
    seed : int
        Seed of the RANSAC plane search (Open3D); the same input gives the same planes.
    """

    lods: tuple[str, ...] = ("1", "2.2")
    plane_distance: float = 0.15
    min_plane_area: float = 2.0
    min_plane_points: int = 12
    max_planes: int = 60
    max_roof_rms: float = 0.5
    lod13_step: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        unknown = [v for v in self.lods if v not in LODS]
        if unknown or not self.lods:
            raise InputError(f"lod.lods {list(self.lods)}: choose among {', '.join(LODS)}")
        for name in ("plane_distance", "min_plane_area", "max_roof_rms", "lod13_step"):
            value = getattr(self, name)
            if not (0.0 < value < 1e6):
                raise InputError(f"lod.{name} {value}: must be a positive number of metres (or m2)")
        if self.min_plane_points < 3 or self.max_planes < 1:
            raise InputError("lod.min_plane_points must be >= 3 and lod.max_planes >= 1")


@dataclass(frozen=True)
class ChangeConfig:
    """Change detection against an older building database (``--old-buildings``).

    Attributes
    ----------
    height_field : str, optional
        The old database's height attribute, when it has none of the usual names
        (``roof_z``, ``height``, ``hauteur``, ``roof_height``, ``h_dak_max``...).
    height_reference : {"ground", "absolute"}, optional
        What the old heights are measured from; by default known from the usual
        names, or decided from the data (``roof_height``), and said in run.json.
    """

    height_field: str | None = None
    height_reference: str | None = None

    def __post_init__(self) -> None:
        if self.height_reference not in (None, "ground", "absolute"):
            raise InputError(f"change.height_reference {self.height_reference!r}: choose ground or absolute")


@dataclass(frozen=True)
class OrthoConfig:
    """True orthophotos of stereo inputs (ortho.tif) and the image-difference check of
    the DSM (ortho_diff.tif). See ``recon3d.stereo.ortho``.

    Attributes
    ----------
    surface : {"dsm", "dtm", "model"}
        What the orthophoto is rectified on: the DSM (a true orthophoto), the DTM
        (buildings lean, as in a classic orthophoto) or the DTM with the building
        model (the model DSM).
    doubtful_threshold : float
        Image difference (1 - NCC, 0 to 2) above which a DSM cell is doubtful.
    doubtful_area : float
        Smallest connected doubtful area (m2) listed in the report.
    textures : bool
        Also write buildings_textured.glb: the model's roofs textured from a true
        orthophoto and its walls from the images (see ``recon3d.stereo.texture``).
    """

    surface: str = "dsm"
    doubtful_threshold: float = 0.6
    doubtful_area: float = 4.0
    textures: bool = True

    def __post_init__(self) -> None:
        if self.surface not in ("dsm", "dtm", "model"):
            raise InputError(f"ortho.surface {self.surface!r}: choose dsm, dtm or model")
        if not (0.0 < self.doubtful_threshold < 2.0) or not (0.0 <= self.doubtful_area < 1e9):
            raise InputError("ortho.doubtful_threshold must lie in (0, 2) and ortho.doubtful_area be >= 0 (m2)")


@dataclass(frozen=True)
class TilesConfig:
    """How the area of a run is cut into work tiles (:mod:`recon3d.pipeline.tiling`).

    Attributes
    ----------
    size : float or None
        Side of a work tile in metres, rounded down to a block of 32 DSM cells times a
        power of two; None: the largest whose points fit one worker's share of the
        memory. The products are the same whatever the size.
    """

    size: float | None = None

    def __post_init__(self) -> None:
        if self.size is not None and not (1.0 <= self.size <= 1e6):
            raise InputError(f"tiles.size {self.size}: between 1 and 1e6 (metres), or unset for automatic")


#: Levels of detail :class:`LodConfig` can build.
LODS = ("1", "1.3", "2.2")


@dataclass(frozen=True)
class PipelineConfig:
    """The whole configuration of ``recon3d run``."""

    stereo: StereoConfig = field(default_factory=StereoConfig)
    dsm: DsmConfig = field(default_factory=DsmConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
    dtm: DtmConfig = field(default_factory=DtmConfig)
    buildings: BuildingsConfig = field(default_factory=BuildingsConfig)
    lod: LodConfig = field(default_factory=LodConfig)
    change: ChangeConfig = field(default_factory=ChangeConfig)
    ortho: OrthoConfig = field(default_factory=OrthoConfig)
    tiles: TilesConfig = field(default_factory=TilesConfig)

    @classmethod
    def from_toml(cls, path: str | Path) -> PipelineConfig:
        """Read a TOML file whose tables are stage names."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"{path}: configuration file not found") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{path}: not valid TOML ({exc})") from None
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "config") -> PipelineConfig:
        """Build from nested dicts, checking every stage and key name."""
        cfg = cls()
        for stage, values in data.items():
            if not isinstance(values, dict):
                raise InputError(f"{source}: [{stage}] must be a table of settings")
            for key, value in values.items():
                cfg = cfg._replace(f"{stage}.{key}", value, source)
        return cfg

    def with_overrides(self, overrides: list[str] | tuple[str, ...]) -> PipelineConfig:
        """Apply ``stage.key=value`` strings; values are parsed as TOML, else as text."""
        cfg = self
        for item in overrides:
            dotted, sep, text = item.partition("=")
            if not sep:
                raise InputError(f"--set {item!r}: expected stage.key=value")
            try:
                value = tomllib.loads(f"v = {text.strip()}")["v"]
            except tomllib.TOMLDecodeError:
                value = text.strip()
            cfg = cfg._replace(dotted.strip(), value, "--set")
        return cfg

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)

    def _replace(self, dotted: str, value: Any, source: str) -> PipelineConfig:
        stage, _, key = dotted.partition(".")
        stages = {f.name: f for f in dataclasses.fields(self)}
        if stage not in stages:
            raise InputError(f"{source}: unknown stage {stage!r}; stages are {', '.join(stages)}")
        section = getattr(self, stage)
        keys = {f.name: f for f in dataclasses.fields(section)}
        if key not in keys:
            raise InputError(
                f"{source}: unknown setting {dotted!r}; {stage} has {', '.join(keys)}"
            )
        value = _coerce(value, typing.get_type_hints(type(section))[key], dotted, source)
        return dataclasses.replace(self, **{stage: dataclasses.replace(section, **{key: value})})


def _coerce(value: Any, hint: Any, dotted: str, source: str) -> Any:
    """Check a value against a field's type hint, converting int to float and lists to tuples."""
    options = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
    if value is None and type(None) in options:
        return None
    for option in options:
        origin = typing.get_origin(option) or option
        if origin is float and isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        if origin is tuple and isinstance(value, list | tuple):
            return tuple(str(v) for v in value)
        if origin in (str, int, bool) and type(value) is origin:
            return value
    raise InputError(f"{source}: {dotted} = {value!r} is not a valid {hint}")
