"""Every lookup path the grid's plan can select, exact against brute force and cKDTree.

D = 3 scans runs of cells (D <= RUN_SCAN_DIMS, unpadded); D = 9 and 17 scan
bucket by bucket with zero-padded rows (17 also bounds entries by their
sketch in phase 2: D > SKETCH_LANES); D = 90 is the paper's colour m = 30.
N = 1 is a linear scan; large N leave phase 1 short of the whole grid, so far
queries reach the coarse phase 2.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from colorps import BucketGrid
from colorps import _grid_kernels as kernels
from tests.conftest import sphere_table
from tests.naive import assert_exact
from tests.test_grid import manifold, noisy


@pytest.mark.parametrize("dims, runs, padded, entry_bound",
                         [(3, True, False, False), (9, False, True, False),
                          (16, False, False, False), (17, False, True, True),
                          (90, False, True, True)])
def test_plan_selects_the_documented_path(dims, runs, padded, entry_bound, rng):
    grid = BucketGrid(manifold(dims, 500, rng), 60)
    plan = grid._data.plan
    assert plan.use_runs == runs
    assert (plan.runs.shape[0] > 0) == runs and (plan.offsets.shape[0] > 0) != runs
    assert (grid._data.entries.values.shape[1] > dims) == padded
    assert grid._data.entries.values.shape[1] % (kernels.LANES if dims > 8 else 1) == 0
    assert plan.entry_bound == entry_bound
    assert not plan.fine_is_all  # N = 60: phase 1 reaches a few cells, phase 2 the rest


@settings(max_examples=40, deadline=None)
@given(dims=st.sampled_from([3, 9, 17, 90]),
       n=st.sampled_from([None, 1, 3, 40, 150]),
       size=st.integers(1, 700),
       sigma=st.sampled_from([0.0, 0.01, 0.3]),
       seed=st.integers(0, 2 ** 32 - 1))
def test_exact_over_dims_grid_sizes_and_noise(dims, n, size, sigma, seed):
    rng = np.random.default_rng(seed)
    table = manifold(dims, size, rng, curvature=rng.uniform(0.2, 3.0))
    far = rng.normal(0, 5, (20, dims)).astype(np.float32)  # phase 2 on large N
    queries = np.concatenate([noisy(table, rng, 150, sigma), far])
    grid = BucketGrid(table, n)
    rows, dist = grid.query(queries, threads=int(rng.integers(1, 3)))
    assert_exact(table, queries, rows, dist)


@pytest.mark.parametrize("m, colour", [(3, False), (5, True), (30, True)])
@pytest.mark.parametrize("theta", [10, 45])
def test_same_distances_as_ckdtree(m, colour, theta, rng):
    """An independent exact method (scipy's k-d tree, float64) agrees on every query."""
    table = sphere_table(m, theta, colour)
    queries = np.concatenate([noisy(table, rng, 2000, 0.01), noisy(table, rng, 300, 0.2)])
    rows, dist = BucketGrid(table).query(queries)
    tree_dist, tree_rows = cKDTree(table.astype(np.float64)).query(queries.astype(np.float64))
    np.testing.assert_allclose(dist, tree_dist, rtol=1e-4, atol=1e-5)
    same = rows == tree_rows
    # Where the rows differ the two entries are tied to float32 precision.
    tie = np.abs(np.linalg.norm(table[rows] - queries, axis=1) - tree_dist) < 1e-5
    assert (same | tie).all()
