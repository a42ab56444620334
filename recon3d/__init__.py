"""recon3d: 3D city reconstruction from point clouds and stereo imagery.

The public API re-exports the core data types and the pipeline entry point.
They are imported on first use (PEP 562 module ``__getattr__``): ``import recon3d``
and the command line's ``--help`` load neither numpy nor any stage's libraries
(trimesh, scipy, open3d, OpenCV, rasterio, pyproj); each stage imports what it needs.
"""

import importlib
import logging

from recon3d.errors import CRSError, DependencyError, InputError, Recon3dError

__version__ = "0.1.0"

logging.getLogger("recon3d").addHandler(logging.NullHandler())

#: Public name -> module defining it, imported on first access.
_LAZY = {
    "AccuracyReport": "recon3d.core.accuracy",
    "Building": "recon3d.core.city",
    "CityModel": "recon3d.core.city",
    "LocalFrame": "recon3d.core.geo",
    "PipelineConfig": "recon3d.config",
    "PointCloud": "recon3d.core.pointcloud",
    "Raster": "recon3d.core.raster",
}


def __getattr__(name: str):
    """Import a lazily exported name of :data:`_LAZY` and cache it in the package."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'recon3d' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


def run(*args, **kwargs):
    """Run the whole pipeline; see :func:`recon3d.pipeline.run.run`."""
    from recon3d.pipeline.run import run as _run

    return _run(*args, **kwargs)


__all__ = [
    "AccuracyReport",
    "Building",
    "CRSError",
    "CityModel",
    "DependencyError",
    "InputError",
    "LocalFrame",
    "PipelineConfig",
    "PointCloud",
    "Raster",
    "Recon3dError",
    "__version__",
    "run",
]
