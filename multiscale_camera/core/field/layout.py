"""Steady grid layouts for rigs in motion: boxes and cells that stay put from frame to
frame while the rig stays inside what they cover.

A grid chosen for each frame alone follows the rig: its first centre sits at the
bundle's corner, its nested levels snap to their parents' lattices wherever the bundle
has moved to, and its cell follows the voxel budget as the bundle grows or shrinks.
Every frame then samples the membership on different voxels, and the rays change by the
grid's discretisation error from one frame to the next however little the rig moved.

A shot's layout (``shot_layout``) is chosen once for all its frames: each level's box
is the union of the boxes its frames ask for, level 0's cell the finest any frame asks
for, laid on a world-fixed lattice: the cell on a ladder of sizes (``CELL_RUNGS``), each
box's faces rounded outwards to multiples of ``SNAP_CELLS`` cells from the world's
origin, a parent's box grown to hold its child's with the parent's margin, and the
cell then coarsened rung by rung until the voxel budget holds the snapped boxes. Every
frame of the shot, rendered in any order by any process, gets the same grids; a frame
whose rig leaves them (``covers``) gets a layout of its own frame alone.
"""

from dataclasses import dataclass

import numpy as np

from .grid import Grid
from .nested import BAND_CELLS, MARGIN_CELLS

# A steady box's faces lie on multiples of this many of its cells (even, so a child's
# faces are centres of its parent): the rig moves that far before a face moves.
SNAP_CELLS = 8
# Rungs of the cell ladder: cells are 2 ** (k / CELL_RUNGS) world units. A cell is first
# rounded down to a rung (at most 4.4% finer than asked), the boxes snapped outwards (up
# to 2 * SNAP_CELLS more cells per axis), and the rung then raised one at a time until
# the snapped grids hold at most the voxel budget, so a steady layout never exceeds it.
CELL_RUNGS = 16
# Rungs a steady layout may climb to fit the budget (a factor 2 ** 6 in the cell, about
# the 1.1 ** 40 ``nested.choose_levels`` allows) before its finest level is given up.
MAX_RUNGS_UP = 6 * CELL_RUNGS


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


def _rung(cell):
    """The index k of the ladder rung 2 ** (k / CELL_RUNGS) at or below ``cell``."""
    return int(np.floor(np.log2(float(cell)) * CELL_RUNGS + 1e-9))


def steady_boxes(boxes, cell, max_voxels=None):
    """Nested grids on the world lattice holding ``boxes``.

    Parameters
    ----------
    boxes : sequence of (lo, hi), (3,) float arrays, world units, coarsest level first:
        the region each level must hold (each child inside its parent's box or not).
    cell : float, world units, the finest level-0 cell asked for (level l's is half
        level l-1's).
    max_voxels : int or None, the budget for all levels together: the rung is raised
        until the snapped grids fit it (None: no budget).

    Returns
    -------
    tuple of Grid, one per box (fewer where the budget cannot hold every level even
    MAX_RUNGS_UP rungs coarser: the finest are given up), each holding its box (and its
    children's with MARGIN_CELLS + BAND_CELLS + 1 of its own cells inside its faces),
    level 0's cell on the ladder at most ``cell`` unless the budget asked for coarser.
    """
    k0 = _rung(cell)
    for count in range(len(boxes), 0, -1):  # the finest level goes where rungs cannot
        for k in range(k0, k0 + MAX_RUNGS_UP + 1):
            grids = _laid_out(boxes[:count], float(2.0 ** (k / CELL_RUNGS)))
            if max_voxels is None or sum(g.size for g in grids) <= max_voxels:
                return grids
    return grids


def _laid_out(boxes, c0):
    """The snapped nested grids of ``boxes`` with level-0 cell ``c0`` (``steady_boxes``)."""
    cells = [c0 / 2**lev for lev in range(len(boxes))]
    out = [None] * len(boxes)
    child = None
    for lev in range(len(boxes) - 1, -1, -1):
        lo, hi = (np.asarray(b, dtype=np.float64) for b in boxes[lev])
        if child is not None:
            keep = (MARGIN_CELLS + BAND_CELLS + 1) * cells[lev]
            lo, hi = np.minimum(lo, child[0] - keep), np.maximum(hi, child[1] + keep)
        child = _snapped(lo, hi, cells[lev])
        out[lev] = child
    return tuple(_grid(lo, hi, cell) for (lo, hi), cell in zip(out, cells, strict=True))


def steady_grid(grid, max_voxels=None):
    """The steady form of a uniform grid: its cell on the ladder, its box (the span of
    its centres) grown to the world lattice of SNAP_CELLS cells, the rung raised until
    ``max_voxels`` (int or None) holds it.

    Parameters
    ----------
    grid : Grid. max_voxels : int or None.

    Returns
    -------
    Grid holding every centre of ``grid``'s box.
    """
    return steady_boxes([grid.bounds], grid.cell, max_voxels)[0]


def steady_levels(grids, max_voxels=None):
    """The steady form of nested grids (coarsest first, each on its parent's half-cell
    lattice, as ``nested.choose_levels`` lays them out): ``steady_boxes`` of their boxes
    and level 0's cell.

    Parameters
    ----------
    grids : sequence of Grid, coarsest first. max_voxels : int or None.

    Returns
    -------
    tuple of Grid, each holding the box of its input; as many levels unless the budget
    cannot hold them (``steady_boxes``).
    """
    return steady_boxes([g.bounds for g in grids], grids[0].cell, max_voxels)


@dataclass(frozen=True, eq=False)
class ShotLayout:
    """The grids of a shot, chosen once for all its frames (``shot_layout``).

    nested : bool, whether the grids are nested levels (else ``grids`` has one).
    grids : tuple of Grid, coarsest first.
    """

    nested: bool
    grids: tuple

    def __eq__(self, other):
        if not isinstance(other, ShotLayout):
            return NotImplemented
        return self.nested == other.nested and self.grids == other.grids

    def __hash__(self):
        return hash((self.nested, self.grids))

    def __repr__(self):
        # part of Settings' repr, so of the field's cache key: every number that matters
        parts = [f"{tuple(g.origin.tolist())}/{g.cell!r}/{g.shape}" for g in self.grids]
        return f"ShotLayout(nested={self.nested}, grids=[{'; '.join(parts)}])"

    def covers(self, grids):
        """Whether these grids hold the boxes of ``grids`` (a frame's own choice,
        coarsest first) level by level, and have at least as many levels."""
        if len(grids) > len(self.grids):
            return False
        for mine, theirs in zip(self.grids, grids):
            lo, hi = mine.bounds
            t_lo, t_hi = theirs.bounds
            if (lo > t_lo + 1e-9).any() or (hi < t_hi - 1e-9).any():
                return False
        return True


def shot_layout(frames, nested, max_voxels):
    """The layout of a shot from the grids each of its frames asks for.

    Parameters
    ----------
    frames : sequence (one per frame) of sequences of Grid, coarsest first: the grids
        ``choose_grid`` (one) or ``nested.choose_levels`` picked for that frame alone.
    nested : bool, as ``ShotLayout.nested``.
    max_voxels : int, the budget for all levels together.

    Returns
    -------
    ShotLayout: as many levels as the frame with most, level l's box the union of the
    frames' level-l boxes, level 0's cell the finest of the frames', on the lattice and
    within the budget (``steady_boxes``).
    """
    count = max(len(f) for f in frames)
    boxes = []
    for lev in range(count):
        have = [f[lev].bounds for f in frames if len(f) > lev]
        boxes.append((np.min([b[0] for b in have], 0), np.max([b[1] for b in have], 0)))
    cell = min(f[0].cell for f in frames)
    return ShotLayout(bool(nested), steady_boxes(boxes, cell, max_voxels))
