"""tools/tangent_table.py: its table reader and the cells it tabulates, against
references written here (what it measured is a trace's deviation, so the reader must
not be the cause)."""

import numpy as np

from fixtures.tools import load_tool
from multiscale_camera.core.field.grid import Grid
from multiscale_camera.core.field.nested import NestedDomain, _aligned_child

tt = load_tool("tangent_table")


def _domain():
    coarse = Grid.from_bounds((-1.0, -0.8, -0.6), (1.0, 0.9, 0.7), 0.1)
    fine = _aligned_child(coarse, np.array([-0.3, -0.2, -0.1]), np.array([0.2, 0.3, 0.25]))
    grids = (coarse, fine)
    return NestedDomain(grids, [np.zeros(g.shape, np.float32) for g in grids])


def test_the_table_reads_a_linear_field_exactly_on_every_level():
    domain = _domain()
    a = np.array([[0.3, -1.2, 2.0], [0.5, 0.1, -0.7], [-1.1, 0.4, 0.9]])
    b = np.array([0.2, -0.4, 1.5])
    # a linear function of the centres, three channels: trilinear reads it exactly
    table = np.concatenate([g.centres(flat=True) @ a.T + b for g in domain.grids])
    rng = np.random.default_rng(5)
    lo, hi = domain.grids[0].bounds
    points = lo + (hi - lo) * rng.random((4000, 3))
    level, _ramp = domain._depth(points)
    assert set(np.unique(level)) == {0, 1}
    np.testing.assert_allclose(tt.read(domain, table, points, level), points @ a.T + b, atol=1e-12)
    # the parent's values where the band blends them: the same function
    fine = np.flatnonzero(level == 1)
    np.testing.assert_allclose(
        tt.read(domain, table, points[fine], level[fine] - 1), points[fine] @ a.T + b, atol=1e-12
    )
