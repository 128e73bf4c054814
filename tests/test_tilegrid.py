"""The tiled cell index of patches, against a dict of the same cells."""

import numba
import numpy as np

from rangesurf._tilegrid import TILE, CellIndex, block_of, find


@numba.njit
def insert(directory, blocks, tiles, column, row, slot):
    block = block_of(directory, blocks, tiles, column, row)
    if block >= 0:
        blocks[block, row & (TILE - 1), column & (TILE - 1)] = slot
    return block >= 0


@numba.njit
def find_all(directory, blocks, tiles, cells):
    found = np.empty(cells.shape[0], np.int64)
    for k in range(cells.shape[0]):
        found[k] = find(directory, blocks, tiles, cells[k, 0], cells[k, 1])
    return found


def test_cells_are_found_where_they_were_put_as_the_index_grows_in_every_direction():
    rng = np.random.default_rng(4)
    # Cells spread over negative and positive coordinates, far beyond the first directory's reach.
    cells = np.unique(rng.integers(-700, 900, size=(5000, 2)).astype(np.int32), axis=0)
    cells = cells[rng.permutation(len(cells))]
    index = CellIndex.of(cells[:100])
    expected = {tuple(cell): slot for slot, cell in enumerate(cells[:100])}
    for slot in range(100, len(cells)):
        column, row = int(cells[slot, 0]), int(cells[slot, 1])
        while not insert(index.directory, index.blocks, index.tiles, np.int32(column), np.int32(row), slot):
            index.make_room(column, row)
        expected[(column, row)] = slot
    np.testing.assert_array_equal(find_all(index.directory, index.blocks, index.tiles, cells), np.arange(len(cells)))
    # Absent cells (inside and far outside the directory) are not found.
    absent = np.array([[c, r] for c, r in rng.integers(-3000, 3000, size=(2000, 2)) if (c, r) not in expected], np.int32)
    assert (find_all(index.directory, index.blocks, index.tiles, absent) == -1).all()
    # Rebuilt from the cells in slot order: the same answers.
    rebuilt = CellIndex.of(cells)
    np.testing.assert_array_equal(find_all(rebuilt.directory, rebuilt.blocks, rebuilt.tiles, cells), np.arange(len(cells)))
    assert (find_all(rebuilt.directory, rebuilt.blocks, rebuilt.tiles, absent) == -1).all()
