"""Open3D, imported without its plotly viewer.

``import open3d`` always imports ``open3d.visualization.draw_plotly``, which pulls in
dash and plotly: about 0.65 s of the 1.1 s import, paid again by every worker process
that segments roofs or ray-casts the city model. recon3d never draws with plotly, so
:func:`open3d` imports Open3D with a stand-in for that one module. The stand-in's
functions import the real module when they are called: ``draw_plotly`` and
``get_plotly_fig`` still work for a user who calls them, and once the import is done
the stand-in is gone from ``sys.modules``.
"""

from __future__ import annotations

import importlib
import sys
import types

__all__ = ["open3d"]

_PLOTLY = "open3d.visualization.draw_plotly"


def open3d() -> types.ModuleType:
    """The ``open3d`` module (imported on the first call, without dash and plotly)."""
    if "open3d" in sys.modules:
        return sys.modules["open3d"]
    stand_in = types.ModuleType(_PLOTLY)
    stand_in.__getattr__ = _deferred  # PEP 562: what `from .draw_plotly import name` asks for
    sys.modules[_PLOTLY] = stand_in
    try:
        import open3d as o3d
    finally:
        if sys.modules.get(_PLOTLY) is stand_in:
            del sys.modules[_PLOTLY]
    return o3d


def _deferred(name: str):
    """A function that imports the real plotly viewer module and calls its ``name``."""
    if name.startswith("__"):
        raise AttributeError(name)

    def call(*args, **kwargs):
        return getattr(importlib.import_module(_PLOTLY), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    return call
