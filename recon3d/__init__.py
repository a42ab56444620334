"""recon3d: 3D city reconstruction from point clouds and stereo imagery.

The public API re-exports the core data types and the pipeline entry point.
Heavy libraries (open3d, pycolmap) are imported only by the stages that use them.
"""

import logging

__version__ = "0.1.0"

logging.getLogger("recon3d").addHandler(logging.NullHandler())

from recon3d.config import PipelineConfig  # noqa: E402
from recon3d.core.accuracy import AccuracyReport  # noqa: E402
from recon3d.core.city import Building, CityModel  # noqa: E402
from recon3d.core.geo import LocalFrame  # noqa: E402
from recon3d.core.pointcloud import PointCloud  # noqa: E402
from recon3d.core.raster import Raster  # noqa: E402
from recon3d.errors import CRSError, DependencyError, InputError, Recon3dError  # noqa: E402


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
