"""A dense, tiled index from 2-D integer cell coordinates to storage slots (the cells of a planar patch).

A patch's cells cover a compact region of its grid, and a frame's points
reach them in scan order: neighbouring points, neighbouring cells. A hash
table (`rangesurf._hashgrid`) scatters neighbours over memory, a cache miss
per lookup once the table outgrows the caches. Here the grid is cut into
tiles of ``TILE`` x ``TILE`` cells; a small dense *directory* gives each
tile's block of ``TILE`` x ``TILE`` slots, allocated when the tile's first
cell appears, and neighbouring cells share a block. The directory covers
the patch's tiles with a margin and grows when a cell falls outside it.
(Simulated Kinect arena, one frame fused into the model of the 40 before it:
fusion 11.0 -> 7.5 ms against the hash table; the pipeline about 3.5 ms per
frame faster.)

State, held by `CellIndex` and passed to the compiled helpers:

* ``directory`` (R, C) int32: the block of each tile, -1 for none;
* ``blocks`` (B, TILE, TILE) int32: the slot of each cell, -1 for none;
* ``tiles`` (3,) int64: the directory's first tile column and row, and the
  blocks in use.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["TILE", "TILE_SHIFT", "CellIndex", "find", "block_of"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")

TILE_SHIFT = 5
TILE = 1 << TILE_SHIFT
_MASK = TILE - 1
# Tiles kept free around the occupied ones when the directory is laid out or grows.
_MARGIN = 4


class CellIndex:
    """The index of one patch's cells (the module docstring says how it is laid out)."""

    def __init__(self, first_column: int, first_row: int, columns: int, rows: int, blocks: int) -> None:
        self.directory = np.full((rows, columns), -1, np.int32)
        self.blocks = np.full((max(blocks, 1), TILE, TILE), -1, np.int32)
        self.tiles = np.array([first_column, first_row, 0], np.int64)

    @classmethod
    def of(cls, coordinates: np.ndarray) -> CellIndex:
        """The index of cells ``(column, row)`` (N, 2) int32 stored in slots 0..N-1."""
        coordinates = np.asarray(coordinates, np.int32).reshape(-1, 2)
        if len(coordinates) == 0:
            return cls(-_MARGIN, -_MARGIN, 2 * _MARGIN + 1, 2 * _MARGIN + 1, 8)
        tile_columns, tile_rows = coordinates[:, 0] >> TILE_SHIFT, coordinates[:, 1] >> TILE_SHIFT
        first_column, first_row = int(tile_columns.min()) - _MARGIN, int(tile_rows.min()) - _MARGIN
        columns = int(tile_columns.max()) + _MARGIN + 1 - first_column
        rows = int(tile_rows.max()) + _MARGIN + 1 - first_row
        occupied = len(np.unique((tile_rows.astype(np.int64) - first_row) * columns + (tile_columns - first_column)))
        index = cls(first_column, first_row, columns, rows, max(8, 2 * occupied))
        _insert_all(index.directory, index.blocks, index.tiles, coordinates)
        return index

    def make_room(self, column: int, row: int) -> None:
        """Grow so that cell (column, row) can be opened: the directory reaches its tile, a block is free."""
        tile_column, tile_row = int(column) >> TILE_SHIFT, int(row) >> TILE_SHIFT
        first_column, first_row = int(self.tiles[0]), int(self.tiles[1])
        rows, columns = self.directory.shape
        if not (first_column <= tile_column < first_column + columns and first_row <= tile_row < first_row + rows):
            # Half the extent again on the side that needs it: a patch that keeps growing grows its directory
            # a bounded number of times per doubling.
            margin_columns, margin_rows = max(_MARGIN, columns // 2), max(_MARGIN, rows // 2)
            new_first_column = min(first_column, tile_column - margin_columns)
            new_first_row = min(first_row, tile_row - margin_rows)
            new_columns = max(first_column + columns, tile_column + margin_columns + 1) - new_first_column
            new_rows = max(first_row + rows, tile_row + margin_rows + 1) - new_first_row
            directory = np.full((new_rows, new_columns), -1, np.int32)
            top, left = first_row - new_first_row, first_column - new_first_column
            directory[top : top + rows, left : left + columns] = self.directory
            self.directory = directory
            self.tiles[0], self.tiles[1] = new_first_column, new_first_row
        if self.tiles[2] >= len(self.blocks):
            self.blocks = np.concatenate([self.blocks, np.full_like(self.blocks, -1)])


@numba.njit(**_JIT, inline="always")
def find(directory, blocks, tiles, column, row):  # pragma: no cover - compiled
    """Slot of cell (column, row), -1 if absent."""
    # One expression, no early return: inlined into a loop, the form with returns (and `_tile_of`) took 2.5
    # times as long (`_touching` on a pipeline's calls, 1.30 -> 0.51 ms).
    tile_row = (row >> TILE_SHIFT) - tiles[1]
    tile_column = (column >> TILE_SHIFT) - tiles[0]
    inside = (tile_row >= 0) & (tile_column >= 0) & (tile_row < directory.shape[0]) & (tile_column < directory.shape[1])
    block = directory[tile_row, tile_column] if inside else -1
    return blocks[block, row & _MASK, column & _MASK] if block >= 0 else -1


@numba.njit(**_JIT, inline="always")
def block_of(directory, blocks, tiles, column, row):  # pragma: no cover - compiled
    """The block holding cell (column, row)'s slot (at ``[row & (TILE - 1), column & (TILE - 1)]``), opened
    if new; -1 when the directory does not reach the cell or no block is free (`CellIndex.make_room`)."""
    tile_row, tile_column = _tile_of(directory, tiles, column, row)
    if tile_row < 0:
        return -1
    block = directory[tile_row, tile_column]
    if block < 0:
        if tiles[2] >= blocks.shape[0]:
            return -1
        block = np.int32(tiles[2])
        tiles[2] += 1
        directory[tile_row, tile_column] = block
    return block


@numba.njit(**_JIT, inline="always")
def _tile_of(directory, tiles, column, row):  # pragma: no cover - compiled
    """The directory entry (row, column) of cell (column, row)'s tile; (-1, -1) when the directory does not reach it."""
    tile_row = (row >> TILE_SHIFT) - tiles[1]
    tile_column = (column >> TILE_SHIFT) - tiles[0]
    if tile_row < 0 or tile_column < 0 or tile_row >= directory.shape[0] or tile_column >= directory.shape[1]:
        return np.int64(-1), np.int64(-1)
    return np.int64(tile_row), np.int64(tile_column)


@numba.njit(**_JIT)
def _insert_all(directory, blocks, tiles, coordinates):  # pragma: no cover - compiled
    """Index cells ``coordinates[k]`` as slot k (the directory reaches them all and has blocks enough)."""
    for k in range(coordinates.shape[0]):
        column, row = coordinates[k, 0], coordinates[k, 1]
        block = block_of(directory, blocks, tiles, column, row)
        blocks[block, row & _MASK, column & _MASK] = k
