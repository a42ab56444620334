"""How much memory recon3d may use, and the guard every large allocation goes through.

The figure is what the system has free (``MemAvailable``, or the cgroup's limit less
what the cgroup uses when lower), capped by the user's ``--max-memory``. The cap is
kept in the ``RECON3D_MAX_MEMORY`` environment variable (bytes), so that worker
processes see it too; it can be set there directly.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

__all__ = ["LIMIT_VARIABLE", "available_memory", "format_size", "limit_memory", "parse_size", "require_memory"]

#: Environment variable holding the user's memory cap in bytes.
LIMIT_VARIABLE = "RECON3D_MAX_MEMORY"

_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def parse_size(text: str) -> int:
    """Bytes of a size such as ``"8G"``, ``"512M"``, ``"1.5 GiB"`` or ``"2000000"``.

    Raises
    ------
    ValueError
        Not a positive size.
    """
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([kKmMgGtT]?)(?:i?[bB])?\s*", str(text))
    if not m or float(m.group(1)) <= 0:
        raise ValueError(f"{text!r} is not a memory size (e.g. 8G, 512M)")
    return int(float(m.group(1)) * _UNITS[m.group(2).upper()])


def format_size(nbytes: float) -> str:
    """``"1.5 GiB"``, ``"300 MiB"``, ``"98 KiB"``: a size for a message."""
    if nbytes >= 2**30:
        return f"{nbytes / 2**30:.1f} GiB"
    return f"{nbytes / 2**20:.0f} MiB" if nbytes >= 2**20 else f"{nbytes / 2**10:.0f} KiB"


def limit_memory(nbytes: int | None) -> None:
    """Cap :func:`available_memory` at ``nbytes`` for this process and its workers (None: no cap)."""
    if nbytes is None:
        os.environ.pop(LIMIT_VARIABLE, None)
    else:
        os.environ[LIMIT_VARIABLE] = str(int(nbytes))


def _limit() -> float:
    try:
        return float(os.environ[LIMIT_VARIABLE])
    except (KeyError, ValueError):
        return float("inf")


def available_memory() -> float:
    """Bytes of memory this process can still use: MemAvailable, or the cgroup's limit if
    lower, capped by ``--max-memory``."""
    available = _limit()
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = min(available, float(line.split()[1]) * 1024)
    except OSError:
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = float(Path("/sys/fs/cgroup/memory.current").read_text())
            available = min(available, float(limit) - used)
    except (OSError, ValueError):
        pass
    return available


def require_memory(need: float, what: str, remedy: str, *, source: object = None) -> None:
    """Raise :class:`~recon3d.errors.MemoryLimitError` unless ``need`` bytes fit in
    :func:`available_memory`.

    The message reads "[source: ]<what> needs about X, more than the Y available
    [(the --max-memory cap)]; <remedy>".
    """
    from recon3d.errors import MemoryLimitError

    available = available_memory()
    if need <= available:
        return
    cap = " (the --max-memory cap)" if available >= _limit() else ""
    where = f"{source}: " if source is not None else ""
    raise MemoryLimitError(
        f"{where}{what} needs about {format_size(need)}, more than the {format_size(available)} available{cap}; {remedy}"
    )
