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
    "DsmConfig",
    "DtmConfig",
    "GroundConfig",
    "LodConfig",
    "PipelineConfig",
    "StereoConfig",
]


@dataclass(frozen=True)
class StereoConfig:
    """Dense matching of frame stereo pairs.

    Attributes
    ----------
    max_disparities : int
        Widest disparity search per pair; the range itself comes from the sparse points.
    min_angle : float
        Smallest ray intersection angle (degrees) for a triangulated point.
    max_parallax : float
        Largest residual vertical parallax (px) accepted after rectification.
    """

    max_disparities: int = 256
    min_angle: float = 1.0
    max_parallax: float = 1.0


@dataclass(frozen=True)
class DsmConfig:
    """Gridding of the point cloud into the DSM.

    Attributes
    ----------
    resolution : float or None
        Cell size in metres; None picks about twice the mean point spacing.
    max_hole_area : float
        Holes up to this area (m2) are filled from their neighbours; larger ones
        (water, occlusions) stay NaN.
    """

    resolution: float | None = None
    max_hole_area: float = 25.0


@dataclass(frozen=True)
class GroundConfig:
    """Ground filtering (progressive morphological filter, SMRF style).

    Attributes
    ----------
    method : {"auto", "smrf", "tophat", "drape", "provider"}
        "auto" picks "smrf" for LiDAR and "tophat" for clouds without return numbers
        (stereo); "provider" trusts the input's class 2. See ``recon3d.terrain.ground``.
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
        Smallest building footprint kept (m2).
    roof_percentile : float
        Percentile of the heights inside a footprint used as the LoD1 roof.
    footprint_shift : float
        Largest map-to-data shift (m) tolerated for given footprints.
    """

    min_height: float = 2.5
    min_area: float = 25.0
    roof_percentile: float = 90.0
    footprint_shift: float = 1.0


@dataclass(frozen=True)
class LodConfig:
    """Which levels of detail are built."""

    lods: tuple[str, ...] = ("1",)


@dataclass(frozen=True)
class PipelineConfig:
    """The whole configuration of ``recon3d run``."""

    stereo: StereoConfig = field(default_factory=StereoConfig)
    dsm: DsmConfig = field(default_factory=DsmConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
    dtm: DtmConfig = field(default_factory=DtmConfig)
    buildings: BuildingsConfig = field(default_factory=BuildingsConfig)
    lod: LodConfig = field(default_factory=LodConfig)

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
