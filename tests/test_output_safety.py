"""Nothing the user had is lost: output folders checked, built aside, published atomically.

The command line runs in a subprocess, as a user runs it: exit status, one line on
stderr naming the file and the problem, no traceback, and the folder around the output
byte for byte as it was (a checksum of every file, hidden ones included).
"""

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import AUTZEN, DELFT, shared


def _cli(*args, cwd=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "recon3d", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


def _snapshot(folder: Path) -> dict:
    """Relative path -> SHA-256 of every file under ``folder`` (and the folders themselves)."""
    out = {}
    for path in sorted(folder.rglob("*")):
        key = str(path.relative_to(folder))
        out[key] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "dir"
    return out


def _refused(result, *needles):
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("recon3d: error: "), result.stderr
    assert "Traceback" not in result.stderr
    for n in needles:
        assert n in lines[0], lines[0]


@pytest.fixture
def cloud_in_folder(tmp_path):
    folder = tmp_path / "data"
    folder.mkdir()
    shutil.copy(shared(AUTZEN), folder / "cloud.laz")
    (folder / "notes.txt").write_text("the user's own file")
    return folder


def test_output_over_the_input_folder_is_refused(cloud_in_folder):
    """``-o <the folder holding IN> --overwrite`` deleted the input and everything beside it."""
    before = _snapshot(cloud_in_folder.parent)
    result = _cli("run", cloud_in_folder / "cloud.laz", "-o", cloud_in_folder, "--overwrite")
    _refused(result, str(cloud_in_folder), "holds the input", "cloud.laz")
    assert _snapshot(cloud_in_folder.parent) == before


def test_output_that_is_or_lies_inside_an_input(tmp_path, cloud_in_folder):
    from recon3d.errors import InputError
    from recon3d.pipeline.output import check_output

    cloud = cloud_in_folder / "cloud.laz"
    with pytest.raises(InputError, match="is the input"):
        check_output(cloud, [cloud], overwrite=True)
    with pytest.raises(InputError, match="lies inside the input"):
        check_output(cloud_in_folder / "out", [cloud_in_folder], overwrite=True)  # a scene folder
    with pytest.raises(InputError, match="holds the input"):
        check_output(tmp_path, [cloud], overwrite=True)  # two levels up
    assert check_output(tmp_path / "out", [cloud], overwrite=False) == (tmp_path / "out").resolve()


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """A finished run of the Delft strip, through the command line."""
    out = tmp_path_factory.mktemp("published") / "out"
    result = _cli("-q", "run", shared(DELFT), "--crs", "EPSG:7415", "-o", out)
    assert result.returncode == 0, result.stderr
    return out


def test_change_keeps_every_earlier_product(published, tmp_path):
    """``change`` checked only changes.geojson and replaced changes.tif and the updated model."""
    out = tmp_path / "out"
    shutil.copytree(published, out)
    (out / "changes.tif").write_bytes(b"an earlier change raster")
    before = _snapshot(tmp_path)
    result = _cli("change", out, "--old-buildings", out / "footprints.geojson")
    _refused(result, "changes.tif", "--overwrite")
    assert _snapshot(tmp_path) == before


def test_export_keeps_the_material_file(published, tmp_path):
    """``export --format obj -o city.obj`` replaced city.mtl beside it."""
    (tmp_path / "city.mtl").write_text("the user's materials")
    before = _snapshot(tmp_path)
    result = _cli("export", published, "--format", "obj", "-o", tmp_path / "city.obj")
    _refused(result, "city.mtl", "--overwrite")
    assert _snapshot(tmp_path) == before


def test_evaluate_keeps_an_existing_json(published, tmp_path):
    (tmp_path / "b.json").write_text("{}")
    result = _cli("evaluate", "buildings", published, "--reference", published / "buildings.city.json",
                  "--json", tmp_path / "b.json")
    _refused(result, "b.json", "--overwrite")
    assert (tmp_path / "b.json").read_text() == "{}"
    result = _cli("evaluate", "buildings", published, "--reference", published / "buildings.city.json",
                  "--json", tmp_path / "b.json", "--overwrite")
    assert result.returncode == 0 and (tmp_path / "b.json").read_text() != "{}"


def test_publishing_swaps_old_and_new_in_one_step(tmp_path, monkeypatch):
    from recon3d.pipeline import output

    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old run")
    for exchange in (True, False):  # renameat2, and the fallback of two renames
        if not exchange:
            monkeypatch.setattr(output, "_exchange", lambda a, b: False)
        work = output.work_folder(out)
        assert work.parent == tmp_path and work.name.startswith(".out.partial-")
        assert (work.stat().st_mode & 0o777) == 0o700  # private, its name unpredictable
        (work / "new.txt").write_text(f"new run {exchange}")
        output.publish(work, out)
        assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
        assert (out / "new.txt").read_text() == f"new run {exchange}"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside


def test_work_folders_of_killed_runs_are_removed(tmp_path):
    """A stale ``.out.partial-PID-*`` of a dead process goes, named in run.json's notes."""
    import json

    stale = tmp_path / ".out.partial-999999999-abc"
    stale.mkdir()
    (stale / "dsm.tif").write_bytes(b"half a raster")
    result = _cli("-q", "run", shared(AUTZEN), "-o", tmp_path / "out")
    assert result.returncode == 0, result.stderr
    assert not stale.exists()
    notes = json.loads((tmp_path / "out" / "run.json").read_text())["notes"]
    assert any(".out.partial-999999999-abc" in n for n in notes)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_ends_the_run_at_once_and_leaves_nothing(tmp_path, sig, code):
    """SIGTERM or Ctrl-C during the building stage with 2 workers: out at once, exit 143 / 130."""
    out = tmp_path / "out"
    # as from a terminal: the test runner's workers may ignore SIGINT, and children inherit that
    proc = subprocess.Popen([sys.executable, "-m", "recon3d", "run", str(shared(DELFT)), "--crs", "EPSG:7415",
                             "-o", str(out), "--workers", "2"], stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(4.0)  # reading, DSM and ground take about 3 s; buildings about 4 s more
    assert proc.poll() is None, "the run ended before the signal"
    os.kill(proc.pid, sig)
    _, err = proc.communicate(timeout=30)  # measured 0.4-0.6 s (20 s before: the pool drained its queue)
    assert proc.returncode == code, err
    assert "interrupted" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_a_signal_that_surfaces_as_another_error_still_ends_as_interrupted(monkeypatch, capsys):
    """A signal inside a compiled module's import (Open3D's, on first use) comes out as
    "ImportError: initialization failed": the run printed a traceback and exited 1."""
    from recon3d import cli

    def interrupted_import(**kwargs):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5.0)
        except SystemExit:
            raise ImportError("initialization failed") from None

    before = {k: signal.getsignal(k) for k in (signal.SIGINT, signal.SIGTERM)}
    monkeypatch.setattr(cli, "cli", interrupted_import)
    monkeypatch.setattr(cli, "_RECEIVED", [])
    try:
        with pytest.raises(SystemExit) as exit_:
            cli.main()
    finally:
        for k, handler in before.items():
            signal.signal(k, handler)
    assert exit_.value.code == 143
    assert "interrupted (terminated)" in capsys.readouterr().err


def test_dot_as_output_and_a_parent_without_write_permission(cloud_in_folder, monkeypatch):
    """``-o .`` in the input's folder crashed; a read-only parent failed after the whole run."""
    from recon3d.errors import InputError
    from recon3d.pipeline import output

    before = _snapshot(cloud_in_folder.parent)
    result = _cli("run", "cloud.laz", "-o", ".", "--overwrite", cwd=cloud_in_folder)
    _refused(result, "holds the input", "cloud.laz")
    assert _snapshot(cloud_in_folder.parent) == before
    # the test may run as root, whom permissions do not stop: ask os.access's answer for a user
    monkeypatch.setattr(output.os, "access", lambda path, mode: Path(path) != cloud_in_folder)
    with pytest.raises(InputError, match="cannot write in .*permission denied"):
        output.check_output(cloud_in_folder / "out", [cloud_in_folder.parent / "elsewhere.laz"], overwrite=False)


def test_work_folders_are_private_and_unpredictable(tmp_path):
    """A symlink planted at the predictable ``.out.partial-<pid>`` redirected the products."""
    from recon3d.pipeline.output import remove_stale, work_folder

    out = tmp_path / "out"
    target = tmp_path / "elsewhere"
    target.mkdir()
    planted = tmp_path / f".out.partial-{os.getpid()}"
    planted.symlink_to(target)
    a, b = work_folder(out), work_folder(out)
    assert a != b and planted not in (a, b) and not a.is_symlink()
    assert (a.stat().st_mode & 0o777) == 0o700
    dead = tmp_path / ".out.partial-999999999-x"
    dead.symlink_to(target)  # a link is never followed nor removed by the clean-up
    remove_stale(out)
    assert dead.is_symlink() and target.is_dir() and list(target.iterdir()) == []
