"""Benchmarks that cannot rot: every ``scripts/bench_*.py`` runs with ``--quick``.

Each runs in its own interpreter on this checkout, on tiny input (a small synthetic
case or a small crop of the shared data, seconds each); a peer tool that is not
installed (CSF, CARS, s2p) is skipped with a printed note. A benchmark given data it
cannot use says so in one line and exits 1. A new ``bench_*.py`` is picked up by the
glob, so it needs a ``--quick`` too. No timing is asserted.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import shared

ROOT = Path(__file__).resolve().parents[1]
BENCHES = sorted(p.name for p in (ROOT / "scripts").glob("bench_*.py"))
#: Benchmarks reading files, given a folder that holds none of them.
WITH_DATA = [n for n in BENCHES if '"--data"' in (ROOT / "scripts" / n).read_text(encoding="utf-8")]

pytestmark = pytest.mark.bench


def _bench(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2")}
    return subprocess.run([sys.executable, str(ROOT / "scripts" / name), *args], capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=600, check=False)  # the timeout only stops a hang


@pytest.mark.parametrize("name", BENCHES)
def test_quick(name, tmp_path):
    shared("")  # the shared data folder: fails in CI, skips elsewhere, when it is missing
    done = _bench(name, "--quick", cwd=tmp_path)
    assert done.returncode == 0, f"{name} --quick failed:\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"
    assert "Traceback" not in done.stderr
    assert done.stdout.strip(), f"{name} --quick printed nothing"


@pytest.mark.parametrize("name", WITH_DATA)
def test_unusable_data_exits_1(name, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    done = _bench(name, "--quick", "--data", str(empty), cwd=tmp_path)
    assert done.returncode == 1, f"{name}: {done.stdout[-1000:]}\n{done.stderr[-2000:]}"
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{name}: ") and str(empty) in last, done.stderr
    assert "Traceback" not in done.stderr


def test_every_bench_has_a_quick_mode():
    assert len(BENCHES) >= 10
    for name in BENCHES:
        assert "_bench.add_quick(parser)" in (ROOT / "scripts" / name).read_text(encoding="utf-8"), name


def _helpers():
    spec = importlib.util.spec_from_file_location("_bench", ROOT / "scripts" / "_bench.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_side_by_side_ratio(capsys):
    helpers = _helpers()
    helpers.print_ratios("scene", "peer", {"rms": 0.5, "s": 2.0}, {"rms": 1.0, "s": 0.0},
                         [("rms", "RMS m"), ("s", "seconds"), ("missing", "other")])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].strip() == "scene: recon3d beside peer"
    assert lines[2].split() == ["RMS", "m", "0.5", "1", "0.50"]
    assert lines[3].split()[-1] == "inf" and lines[4].split()[-1] == "nan"


def test_peer_missing(capsys):
    helpers = _helpers()
    helpers.peer_missing("CSF", "pip install x", quick=True)
    assert "note: CSF is not installed" in capsys.readouterr().out
    with pytest.raises(SystemExit) as stop:
        helpers.peer_missing("CSF", "pip install x", quick=False)
    assert stop.value.code == 1 and "pip install x" in capsys.readouterr().err


def test_profile_run_prints_the_top_functions_of_each_terrain_stage(tmp_path):
    shared("")
    done = _bench("profile_run.py", "--quick", "--top", "5", cwd=tmp_path)
    assert done.returncode == 0, f"{done.stdout[-2000:]}\n{done.stderr[-4000:]}"
    for stage in ("dsm", "ground", "dtm"):
        block = done.stdout.split(f"== {stage}: ")[1].split("\n== ")[0]
        assert "tottime" in block and len(block.strip().splitlines()) >= 3, block


def _load_bench(name: str):
    """The module of ``scripts/<name>.py`` (which imports ``_bench`` beside it)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
        bench = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(bench)
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    return bench


def _frame_stereo_bench():
    return _load_bench("bench_frame_stereo")


def test_frame_stereo_bench_runs_random_surveys_by_name(tmp_path):
    """``--only random_N`` runs the family's random survey of seed N, as the closing
    notes name them; a name that is neither refuses in one line."""
    bench = _frame_stereo_bench()
    from recon3d.synthetic.family import CONFIGURATIONS, random_spec

    assert bench.survey("random_52") == random_spec(52)
    assert bench.survey("nadir_pair") == CONFIGURATIONS["nadir_pair"]
    assert bench.survey("random_") is None and bench.survey("random_x") is None and bench.survey("nadir") is None
    done = _bench("bench_frame_stereo.py", "--only", "random_x", cwd=tmp_path)
    assert done.returncode == 1 and "random_N" in done.stderr and "Traceback" not in done.stderr


def test_frame_stereo_bench_keeps_rendered_scenes(tmp_path):
    """``--scenes DIR``: a scene is rendered once and found again, byte for byte; another
    spec or another number of rays per pixel is another scene, and a scene rendered
    without the folder goes to the run's own temporary folder."""
    from recon3d.synthetic.family import CONFIGURATIONS

    bench = _frame_stereo_bench()
    spec = CONFIGURATIONS["nadir_pair"].with_width(160)
    scenes = tmp_path / "scenes"
    first, seconds = bench.render(spec, 1, tmp_path / "run1", scenes)
    assert seconds > 0 and first.parent == scenes and (first / "truth" / "scene.json").exists()
    files = {p.relative_to(first): p.read_bytes() for p in sorted(first.rglob("*")) if p.is_file()}
    again, seconds = bench.render(spec, 1, tmp_path / "run2", scenes)
    assert again == first and seconds == 0.0
    assert files == {p.relative_to(first): p.read_bytes() for p in sorted(first.rglob("*")) if p.is_file()}
    assert bench.scene_key(spec, 3) != bench.scene_key(spec, 1)
    assert bench.scene_key(spec.with_width(200), 1) != bench.scene_key(spec, 1)
    assert [p.name for p in scenes.iterdir()] == [first.name]  # no scratch left behind
    alone, _ = bench.render(spec, 1, tmp_path / "run3")
    assert alone == tmp_path / "run3" / spec.name and (alone / "truth" / "scene.json").exists()


def test_scale_bench_splits_the_speed_up_by_stage():
    """The per-stage table of ``bench_scale.py --compare-workers``: a stage halved by two
    workers idles nothing, one not sped up idles half its single-worker time; stages
    under 0.5 s are left out, the total keeps them."""
    lines = _load_bench("bench_scale").speedup_table({"lod": 10.0, "dtm": 3.0, "read": 0.2}, {"lod": 5.0, "dtm": 3.0, "read": 0.2}, 2)
    rows = {line.split()[0]: line.split()[1:] for line in lines.splitlines()[1:]}
    assert rows["lod"] == ["10.0", "5.0", "2.00", "0.0"]
    assert rows["dtm"] == ["3.0", "3.0", "1.00", "1.5"]
    assert "read" not in rows
    assert rows["all"] == ["stages", "13.2", "8.2", "1.61", "1.6"]
