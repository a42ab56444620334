"""The output folder of a run: its products' names, checked first, built aside,
published in one step, and read back by the commands that work on a finished run.

A run never writes into its output folder while it works. It checks the folder before
anything is read (not the input itself, not inside or around any input, not a
non-empty folder without ``--overwrite``), builds the products in a private work folder
beside it (``tempfile.mkdtemp``: an unpredictable name, mode 0700, so a planted
symlink cannot redirect it), and publishes it by swapping it with the old output in
one ``renameat2(RENAME_EXCHANGE)`` call: whenever the process dies, the output folder
holds the old run or the new one. Work folders left by killed runs are removed by the
next run of the same output, which says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import logging
import os
import shutil
import tempfile
from pathlib import Path

from recon3d.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["FINGERPRINT", "WORK_CACHE", "FinishedRun", "Products", "adopt", "check_output", "count_results", "publish",
           "remove_stale", "work_folder"]


class Products:
    """The names of the products in a run's output folder (DESIGN.md's contract)."""

    DSM = "dsm.tif"
    DTM = "dtm.tif"
    NDSM = "ndsm.tif"
    MODEL_DSM = "model_dsm.tif"
    CLOUD = "cloud.laz"
    CITY = "buildings.city.json"
    OBJ = "buildings.obj"
    GLB = "buildings.glb"
    GLB_TEXTURED = "buildings_textured.glb"
    TILES = "buildings_3dtiles"
    FOOTPRINTS = "footprints.geojson"
    FOOTPRINTS_GPKG = "footprints.gpkg"
    ORTHO = "ortho.tif"
    ORTHO_DIFF = "ortho_diff.tif"
    CHANGES = "changes.geojson"
    CHANGES_RASTER = "changes.tif"
    UPDATED_CITY = "buildings_updated.city.json"
    REPORT = "report.json"
    RUN = "run.json"


class FinishedRun:
    """A finished run's output folder, read by ``recon3d change``, ``export``, ``evaluate``.

    Parameters
    ----------
    folder : Path
    """

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)

    def path(self, name: str, *, required: bool = True) -> Path:
        """The product ``name`` (a :class:`Products` name).

        Raises
        ------
        InputError
            It is missing (``required``): the folder is no finished run, or not this one's kind.
        """
        path = self.folder / name
        if required and not path.exists():
            what = "not a folder" if not self.folder.is_dir() else f"no {name} in it"
            raise InputError(f"{self.folder}: not the output folder of a finished recon3d run ({what})")
        return path

    def city(self, **options):
        """The buildings (buildings.city.json; ``options`` as in :func:`recon3d.io.cityjson.read_cityjson`)."""
        from recon3d.io.cityjson import read_cityjson

        return read_cityjson(self.path(Products.CITY), **options)

    def raster(self, name: str):
        """One of the run's rasters (:class:`~recon3d.core.raster.Raster`)."""
        from recon3d.io.geotiff import read_raster

        return read_raster(self.path(name))

#: Sub-folder of a work folder holding what a resumed run can take up (the points in
#: buckets, each tile's results); removed before the products are published.
WORK_CACHE = "_work"

#: File of :data:`WORK_CACHE` naming the inputs and settings its work belongs to.
FINGERPRINT = "fingerprint.json"

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def check_output(out_dir: Path, inputs: list[Path], *, overwrite: bool) -> Path:
    """The resolved output folder, after checking it may be (re)placed.

    Raises
    ------
    InputError
        When ``out_dir`` is an input, holds an input (``--overwrite`` would delete it),
        lies inside an input folder, is a file, or is a non-empty folder and
        ``overwrite`` is False.
    """
    out = Path(out_dir).expanduser().resolve()
    for given in inputs:
        inp = Path(given).expanduser().resolve()
        if out == inp:
            raise InputError(f"{out_dir}: the output folder is the input {given}; choose another -o")
        if out in inp.parents:
            raise InputError(
                f"{out_dir}: the output folder holds the input {given}; replacing it would delete the input. "
                "Choose another -o"
            )
        if inp in out.parents:
            raise InputError(f"{out_dir}: the output folder lies inside the input {given}; choose another -o")
    if out == Path(out.anchor):
        raise InputError(f"{out_dir}: the output folder cannot be a file system's root")
    if out.exists() and not out.is_dir():
        raise InputError(f"{out_dir}: exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise InputError(f"{out_dir}: output folder exists and is not empty; use --overwrite to replace it")
    parent = out.parent
    if parent.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{out_dir}: cannot write in {parent} (permission denied)")
    return out


def _prefix(out: Path, kind: str) -> str:
    return f".{out.name}.{kind}-{os.getpid()}-"


def work_folder(out: Path) -> Path:
    """A new private folder beside ``out`` (created with its parents), for the run's products."""
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=_prefix(out, "partial"), dir=out.parent))


def remove_stale(out: Path) -> list[str]:
    """Remove work folders of earlier runs of ``out`` whose process is gone; a note for each."""
    notes = []
    if not out.parent.is_dir():
        return notes
    for path in sorted(out.parent.glob(f".{out.name}.*-*-*")):
        kind, _, rest = path.name[len(out.name) + 2 :].partition("-")
        pid = rest.split("-", 1)[0]
        if kind not in ("partial", "old") or not pid.isdigit() or _alive(int(pid)) or path.is_symlink():
            continue
        shutil.rmtree(path, ignore_errors=True)
        notes.append(f"removed {path.name}, left beside {out.name} by a run that was killed (process {pid})")
        log.info(notes[-1])
    return notes


def adopt(out: Path, fingerprint: dict, cache: Path) -> bool:
    """Take up the work of a killed or failed run of ``out`` (``--resume``): move its
    :data:`WORK_CACHE` to ``cache``. False when there is none.

    Raises
    ------
    InputError
        The work left there belongs to other inputs or settings.
    """
    import json

    if not out.parent.is_dir():
        return False
    for path in sorted(out.parent.glob(f".{out.name}.partial-*-*")):
        pid = path.name[len(out.name) + 2 :].partition("-")[2].split("-", 1)[0]
        old = path / WORK_CACHE
        if path.is_symlink() or not pid.isdigit() or _alive(int(pid)) or not (old / FINGERPRINT).is_file():
            continue
        try:
            theirs = json.loads((old / FINGERPRINT).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if theirs != json.loads(json.dumps(fingerprint, sort_keys=True)):
            differ = sorted(k for k in set(theirs) | set(fingerprint) if theirs.get(k) != fingerprint.get(k))
            raise InputError(f"{path}: the work left there is of a different run ({', '.join(differ)} differ); "
                             "run without --resume to start afresh (it is then removed)")
        old.rename(cache)
        return True
    return False


def count_results(cache: Path) -> int:
    """Tile results kept in a work cache."""
    return sum(1 for _ in cache.glob("tiles-*/*/*.npz"))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def publish(work_dir: Path, out: Path) -> None:
    """Put the finished ``work_dir`` at ``out``, replacing an old output in one atomic swap.

    Where the file system cannot swap (no ``renameat2``), the old output is renamed
    aside first and put back should the second rename fail.
    """
    if not out.exists():
        os.rename(work_dir, out)
        return
    if _exchange(work_dir, out):
        _remove(work_dir)  # now the old output
        return
    old = Path(tempfile.mkdtemp(prefix=_prefix(out, "old"), dir=out.parent))
    os.replace(out, old / "run")
    try:
        os.rename(work_dir, out)
    except OSError:
        os.replace(old / "run", out)
        raise
    finally:
        shutil.rmtree(old, ignore_errors=True)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically (Linux ``renameat2``); False where it is not supported."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError, TypeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))
