"""Whole-area grids kept in files of the work folder, mapped into the run's process.

The stages between the tile passes work on whole-area grids (DSM, DTM, nDSM, the
building labels...), and the run's process holds them while the workers build the
solids and scan the model: memory that grows with the area, not with the tile. Once
the buildings are found, those grids are written to the work folder and mapped
(``mmap``, shared), so they are the same arrays to every reader while their pages
belong to the system's page cache: after each stage :meth:`Spill.release` hands them
back (``MADV_DONTNEED``), and a stage that reads a grid again pages it in from the
cache, or from the disk when the system needed the memory meanwhile.
"""

from __future__ import annotations

import mmap
from pathlib import Path

import numpy as np

__all__ = ["Spill"]


class Spill:
    """The grids of one run mapped from files of ``folder``.

    Parameters
    ----------
    folder : Path
        Where the grids' files go (the run's work folder, removed with it).
    """

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self._maps: list[mmap.mmap] = []

    def __call__(self, array: np.ndarray) -> np.ndarray:
        """``array``'s values, from a mapped file: (rows, cols) of the same dtype, writable."""
        array = np.ascontiguousarray(array)
        if array.nbytes == 0:
            return array
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / f"grid{len(self._maps)}.{array.dtype.str.strip('<>|=')}"
        array.tofile(path)
        with open(path, "r+b") as f:
            mapped = mmap.mmap(f.fileno(), array.nbytes)  # shared: what is written goes to the file
        self._maps.append(mapped)
        return np.frombuffer(mapped, array.dtype).reshape(array.shape)

    def release(self) -> None:
        """Hand the grids' pages back to the system (they stay in its page cache)."""
        if not hasattr(mmap, "MADV_DONTNEED"):
            return
        for mapped in self._maps:
            mapped.madvise(mmap.MADV_DONTNEED)
