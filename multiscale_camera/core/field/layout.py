"""Steady grid layouts for rigs in motion: boxes and cells that stay put from frame to
frame while the rig stays inside what they cover.

A grid chosen for each frame alone follows the rig: its first centre sits at the
bundle's corner, its nested levels snap to their parents' lattices wherever the bundle
has moved to. Every frame then samples the membership on different voxels, and the rays
change by the grid's discretisation error from one frame to the next however little the
rig moved. Here every box is laid on a world-fixed lattice: the cell is rounded down to a
ladder of sizes (``CELL_LADDER``: a zoom changes it only when it crosses a rung), each
box's faces are rounded outwards to multiples of ``SNAP_CELLS`` cells from the world's
origin, and a parent's box grows to hold its child's with the parent's margin. The
layout is a function of the frame's rig alone (a frame rendered cold gets the layout a
sequence gave it), and neighbouring frames share it until the rig leaves its boxes.
"""

import numpy as np

from .grid import Grid
from .nested import BAND_CELLS, MARGIN_CELLS

# A steady box's faces lie on multiples of this many of its cells (even, so a child's
# faces are centres of its parent): the rig moves that far before a face moves.
SNAP_CELLS = 8
# Rungs of the cell ladder: cells are rounded down to 2 ** (k / CELL_RUNGS) world units,
# at most 4.4% finer than asked (14% more voxels at worst).
CELL_RUNGS = 16


def ladder_cell(cell):
    """``cell`` (float, world units, > 0) rounded down to the ladder 2 ** (k / CELL_RUNGS)."""
    k = np.floor(np.log2(float(cell)) * CELL_RUNGS + 1e-9)
    return float(2.0 ** (k / CELL_RUNGS))


def _snapped(lo, hi, cell):
    """(lo, hi) rounded outwards to multiples of SNAP_CELLS * ``cell`` from the origin."""
    q = SNAP_CELLS * cell
    return np.floor(np.asarray(lo) / q + 1e-9) * q, np.ceil(np.asarray(hi) / q - 1e-9) * q


def _grid(lo, hi, cell):
    shape = tuple(int(n) for n in np.rint((hi - lo) / cell).astype(int) + 1)
    return Grid(lo, cell, shape)


def steady_grid(grid):
    """The steady form of a uniform grid: its cell on the ladder, its box (the span of
    its centres) grown to the world lattice of SNAP_CELLS cells.

    Parameters
    ----------
    grid : Grid.

    Returns
    -------
    Grid holding every centre of ``grid``'s box, cell at most ``grid.cell``.
    """
    cell = ladder_cell(grid.cell)
    return _grid(*_snapped(*grid.bounds, cell), cell)


def steady_levels(grids):
    """The steady form of nested grids (coarsest first, each on its parent's half-cell
    lattice, as ``nested.choose_levels`` lays them out): level 0's cell on the ladder,
    every level's cell half its parent's, every box grown to its world lattice, finest
    first, and each parent's box grown to hold its child's MARGIN_CELLS + BAND_CELLS
    (plus one) of the parent's cells inside its faces.

    Parameters
    ----------
    grids : sequence of Grid, coarsest first.

    Returns
    -------
    tuple of Grid, the same number of levels, each holding the box of its input.
    """
    c0 = ladder_cell(grids[0].cell)
    cells = [c0 / 2**lev for lev in range(len(grids))]
    boxes = [g.bounds for g in grids]
    out = [None] * len(grids)
    child = None
    for lev in range(len(grids) - 1, -1, -1):
        lo, hi = boxes[lev]
        if child is not None:
            keep = (MARGIN_CELLS + BAND_CELLS + 1) * cells[lev]
            lo, hi = np.minimum(lo, child[0] - keep), np.maximum(hi, child[1] + keep)
        child = _snapped(lo, hi, cells[lev])
        out[lev] = child
    return tuple(_grid(lo, hi, cell) for (lo, hi), cell in zip(out, cells, strict=True))
