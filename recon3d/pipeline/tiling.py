"""Work tiles: the run's area cut into squares of whole DSM cells, each read with a buffer.

Tiles are nodes of a quadtree over the DSM grid: squares of ``BLOCK * 2**k`` cells from
the grid's corner. Every cell belongs to exactly one tile's core, every point to the
tile of its cell, and the tiles are visited in Morton (Z) order. A point's place in
cloud.laz is then its block's Morton code (then its coordinates), which every tile
size puts in the same order: an aligned square of blocks is one run of Morton codes.

A tile reads its core's points and those of a buffer around it, at least as wide as
the farthest any per-point operator looks (the neighbours of the vegetation test, the
terrain's gradient, the nearest point of the accuracy grid); what it computes for its
core points is then what the whole survey gives them, to the bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["BLOCK", "Tile", "TileGrid", "morton", "plan_tiles"]

#: Cells on the side of a block, the unit of the quadtree and of cloud.laz's point order.
BLOCK = 32


def morton(row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """(n,) uint64 Morton (Z-order) code of non-negative (row, col) pairs below 2**31."""
    def spread(v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, np.uint64) & np.uint64(0xFFFFFFFF)
        for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF), (4, 0x0F0F0F0F0F0F0F0F),
                            (2, 0x3333333333333333), (1, 0x5555555555555555)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        return v

    return (spread(row) << np.uint64(1)) | spread(col)


@dataclass(frozen=True)
class Tile:
    """One work tile: its key in the quadtree level and its core cells in the DSM grid.

    Attributes
    ----------
    key : (row, col)
        Position among the tiles of its level.
    rows, cols : slice
        Core cells (clipped to the grid).
    """

    key: tuple[int, int]
    rows: slice
    cols: slice

    @property
    def name(self) -> str:
        return f"{self.key[0]}_{self.key[1]}"

    def window(self, buffer: int, shape: tuple[int, int]) -> tuple[slice, slice]:
        """The core widened by ``buffer`` cells on every side, clipped to the grid of ``shape``."""
        return (slice(max(self.rows.start - buffer, 0), min(self.rows.stop + buffer, shape[0])),
                slice(max(self.cols.start - buffer, 0), min(self.cols.stop + buffer, shape[1])))


@dataclass(frozen=True)
class TileGrid:
    """The tiles of a run.

    Attributes
    ----------
    shape : (rows, cols)
        The DSM grid.
    size : int
        Side of a tile in cells, ``BLOCK * 2**level``.
    buffer : int
        Cells read around each tile's core.
    """

    shape: tuple[int, int]
    size: int
    buffer: int

    def tiles(self, occupied: np.ndarray | None = None) -> list[Tile]:
        """The tiles, in Morton order; with ``occupied`` ((rows, cols) of blocks, bool),
        only those holding a block with points."""
        rows, cols = (-(-n // self.size) for n in self.shape)
        keys = np.argwhere(np.ones((rows, cols), bool))
        if occupied is not None:
            per = self.size // BLOCK
            tr, tc = np.nonzero(occupied)
            keys = np.unique(np.column_stack([tr // per, tc // per]), axis=0)
        keys = keys[np.argsort(morton(keys[:, 0], keys[:, 1]), kind="stable")]
        s = self.size
        return [Tile((int(r), int(c)), slice(r * s, min((r + 1) * s, self.shape[0])),
                     slice(c * s, min((c + 1) * s, self.shape[1]))) for r, c in keys]


def plan_tiles(
    shape: tuple[int, int], buffer: int, points_per_cell: float, *, budget: float, size: int | None = None
) -> tuple[TileGrid, str]:
    """Choose the tile size of a run and say why.

    Parameters
    ----------
    shape : (rows, cols)
        The DSM grid.
    buffer : int
        Cells read around each tile's core.
    points_per_cell : float
        Mean points per DSM cell where there are points.
    budget : float
        Points one tile may hold, buffer included (the memory model's figure).
    size : int, optional
        The user's tile side in cells; rounded down to ``BLOCK * 2**k`` (at least one block).

    Returns
    -------
    TileGrid
    reason : str
    """
    whole = BLOCK * 2 ** max(0, math.ceil(math.log2(max(max(shape) / BLOCK, 1.0))))
    if size is not None:
        side = BLOCK * 2 ** max(0, int(math.floor(math.log2(max(size / BLOCK, 1.0)))))
        side = min(side, whole)
        return TileGrid(shape, side, buffer), f"tiles.size: {size} cells, rounded down to {side} (a block times a power of two)"
    side = whole
    while side > BLOCK and (side + 2 * buffer) ** 2 * points_per_cell > budget:
        side //= 2
    if side == whole:
        return TileGrid(shape, side, buffer), f"one tile: the whole area holds fewer than {budget:,.0f} points"
    return TileGrid(shape, side, buffer), (
        f"largest tile whose {(side + 2 * buffer) ** 2 * points_per_cell:,.0f} points (with the buffer) "
        f"fit a tile's budget of {budget:,.0f} (the lesser of one worker's share of the memory "
        "and the cap on a tile's points)"
    )
