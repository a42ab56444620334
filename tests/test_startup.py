"""Start-up: ``import recon3d`` and the command line load no heavy library.

``recon3d --help`` and ``--version`` must answer at once (issue 22): the stages import
trimesh, scipy, open3d, OpenCV, rasterio... when they run, not when the package or the
CLI is imported. Checked functionally, in a fresh interpreter, by what is in
``sys.modules``; no timing.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Libraries that must not be imported by ``import recon3d, recon3d.cli`` (the issue's
#: four first; the others cost tenths of a second each too).
HEAVY = ("trimesh", "scipy.spatial", "open3d", "cv2", "scipy", "numpy", "rasterio", "pyproj", "laspy",
         "shapely", "pycolmap", "dask", "tqdm", "numba")


def _modules_after(code: str) -> set[str]:
    """Names in ``sys.modules`` after running ``code`` in a fresh interpreter on this checkout."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    script = f"{code}\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=ROOT,
                          check=False)
    assert done.returncode == 0, done.stderr
    return set(json.loads(done.stdout.strip().splitlines()[-1]))


def test_import_loads_no_heavy_library():
    modules = _modules_after("import recon3d, recon3d.cli\nassert recon3d.__file__.startswith(%r)" % str(ROOT))
    loaded = [m for m in HEAVY if m in modules]
    assert not loaded, f"import recon3d / recon3d.cli loaded {loaded}"


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["run", "--help"], ["evaluate", "ground", "--help"]])
def test_help_and_version_load_no_heavy_library(argv):
    code = ("import contextlib, io\nfrom recon3d.cli import main\nimport sys\n"
            f"sys.argv = ['recon3d', *{argv!r}]\n"
            "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n    main()")
    modules = _modules_after(code)
    loaded = [m for m in HEAVY if m in modules]
    assert not loaded, f"recon3d {' '.join(argv)} loaded {loaded}"


def test_public_names_still_importable():
    """The lazily exported names are the real classes, listed by dir() and star-import."""
    import recon3d
    from recon3d.core.city import CityModel
    from recon3d.core.raster import Raster

    assert recon3d.CityModel is CityModel and recon3d.Raster is Raster
    assert set(recon3d.__all__) <= set(dir(recon3d))
    namespace: dict = {}
    exec("from recon3d import *", namespace)
    assert {"PointCloud", "PipelineConfig", "LocalFrame", "AccuracyReport", "run"} <= set(namespace)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        recon3d.nope  # noqa: B018


def test_open3d_comes_without_its_plotly_viewer_which_still_works_when_called():
    """Roof segmentation and the model DSM import Open3D in every worker; its plotly
    viewer (dash, plotly: about 0.65 s) is left out until someone calls it."""
    code = (
        "import numpy as np, sys\nfrom recon3d.core.o3d import open3d\no3d = open3d()\n"
        "assert 'dash' not in sys.modules and 'plotly' not in sys.modules, 'viewer imported'\n"
        "cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).random((50, 3))))\n"
        "plane, inliers = cloud.segment_plane(0.01, 3, 50)\nassert len(plane) == 4\n"
        "assert o3d.t.geometry.RaycastingScene() is not None\n"
        "assert open3d() is o3d\n"
        "figure = o3d.visualization.get_plotly_fig([cloud])\n"
        "assert type(figure).__module__.startswith('plotly'), type(figure)\n"
        "assert hasattr(sys.modules['open3d.visualization.draw_plotly'], 'Dash')\n"
    )
    modules = _modules_after(code)
    assert "dash" in modules and "open3d" in modules
