"""What every ``scripts/bench_*.py`` shares: ``--quick``, refusing unusable data, peers side by side.

- ``--quick`` runs a benchmark on tiny input (a small synthetic case or a small crop
  of the shared data) in seconds; ``tests/test_benchmarks.py`` runs every benchmark so,
  so none can rot unnoticed. Its figures only show that the benchmark still works.
- :func:`refuse` ends a benchmark given data it cannot use: one line on stderr naming
  the benchmark, the data and the problem, exit status 1 (:func:`guard` turns a recon3d
  input error, a missing file or an unreadable image into the same).
- :func:`peer_missing`: a peer tool (CSF, CARS, s2p) that is not installed is skipped
  with a printed note in ``--quick``; a full run refuses, naming how to install it.
- :func:`print_ratios` prints recon3d's and a peer's figures side by side with their ratio.

Scripts import it as ``_bench`` (``scripts/`` is on ``sys.path`` when one runs).
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"

QUICK_HELP = "tiny input, a few seconds: checks the benchmark still runs (the test suite runs it so)"


def add_quick(parser: argparse.ArgumentParser) -> None:
    """Add the ``--quick`` flag."""
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)


def _name() -> str:
    return Path(sys.argv[0]).name or "benchmark"


def refuse(message: str) -> NoReturn:
    """Say why the benchmark cannot run on what it was given (stderr, one line) and exit 1."""
    print(f"{_name()}: {message}", file=sys.stderr)
    raise SystemExit(1)


def require(path: Path, what: str) -> Path:
    """``path`` when it exists, else :func:`refuse` naming ``what`` it should be."""
    if not Path(path).exists():
        refuse(f"{path}: {what} not found")
    return Path(path)


def guard(main: Callable[[], object]) -> None:
    """Run ``main``; unusable input (recon3d input errors, missing or unreadable files) exits 1 in one line."""
    from recon3d.errors import Recon3dError

    try:
        result = main()
    except BrokenPipeError:  # stdout closed early (| head): not the data's fault
        raise
    except Exception as exc:
        if not _data_error(exc, Recon3dError):
            raise
        refuse(f"cannot use the data: {exc}")
    raise SystemExit(result if isinstance(result, int) else 0)


def _data_error(exc: Exception, recon3d_error: type) -> bool:
    """True for errors an unusable input causes: recon3d's, file system, raster, LAS and CRS readers'."""
    return isinstance(exc, recon3d_error | OSError) or type(exc).__module__.split(".")[0] in ("rasterio", "laspy", "pyproj")


def peer_missing(peer: str, install: str, quick: bool) -> None:
    """A peer that is not installed: a note in ``--quick``, else :func:`refuse` naming how to install it."""
    if not quick:
        refuse(f"{peer} is not installed ({install}); --quick runs without it")
    print(f"note: {peer} is not installed ({install}); skipped in --quick, recon3d's side only")


#: How to get PDAL, the peer of the terrain and ground benchmarks (never a dependency).
PDAL_INSTALL = "conda-forge pdal, Ubuntu's apt pdal, or on Debian: sudo sh scripts/pdal_chroot.sh"


def use_pdal(skip: bool, quick: bool) -> bool:
    """Whether a benchmark runs PDAL beside recon3d: on the PATH and not skipped
    (``--no-pdal``); missing, :func:`peer_missing` says how to install it."""
    if skip:
        return False
    if shutil.which("pdal") is None:
        peer_missing("PDAL", PDAL_INSTALL, quick)
        return False
    return True


def pdal_command(*args: str) -> list[str]:
    """The command line running ``pdal`` with ``args``."""
    return [shutil.which("pdal") or "pdal", *args]


def peer_failed(peer: str, why: str, quick: bool) -> None:
    """A peer that is installed but failed: a note in ``--quick`` (its column left out), else :func:`refuse`."""
    why = why.strip().splitlines()[-1] if why.strip() else "no message"
    if not quick:
        refuse(f"{peer} failed: {why}")
    print(f"note: {peer} failed ({why}); left out in --quick, recon3d's side only")


def ratio(a, b) -> float:
    """``a / b``; NaN when either is missing, infinite for ``b == 0 < a``."""
    if not isinstance(a, int | float) or not isinstance(b, int | float) or math.isnan(a) or math.isnan(b):
        return math.nan
    if b == 0:
        return 1.0 if a == 0 else math.inf
    return a / b


def print_ratios(title: str, peer: str, ours: dict, theirs: dict, keys: list[tuple[str, str]]) -> None:
    """One block: each figure of ``keys`` (key, label) for recon3d and ``peer``, and recon3d / peer."""
    print(f"  {title}: recon3d beside {peer}")
    width = max(11, len(peer) + 2)  # a long peer name ("recon3d before") keeps its column apart
    print(f"    {'figure':<22}{'recon3d':>11}{peer:>{width}}{'ratio':>8}")
    for key, label in keys:
        a, b = ours.get(key), theirs.get(key)
        cells = [f"{v:>{w}.4g}" if isinstance(v, int | float) else f"{'-':>{w}}" for v, w in ((a, 11), (b, width))]
        print(f"    {label:<22}{''.join(cells)}{ratio(a, b):>8.2f}")
