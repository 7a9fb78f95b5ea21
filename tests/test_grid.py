import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from colorps import BucketGrid, InputError
from tests.conftest import sphere_table
from tests.naive import assert_exact, nearest_distances


def manifold(dims, size, rng, curvature=1.0):
    """A smooth random 2-D manifold embedded in R^dims."""
    uv = rng.random((size, 2)) * 2 - 1
    freq = rng.normal(size=(2, dims)) * curvature
    phase = rng.random(dims) * 2 * np.pi
    lin = rng.normal(size=(2, dims))
    return (uv @ lin + 0.3 * np.sin(uv @ freq + phase)).astype(np.float32)


def noisy(table, rng, count, sigma):
    pick = rng.integers(0, table.shape[0], count)
    return (table[pick] + rng.normal(0, sigma, (count, table.shape[1]))).astype(np.float32)


@pytest.mark.parametrize("dims", [2, 3, 5, 12, 30, 90])
@pytest.mark.parametrize("sigma", [0.0, 0.01, 0.1])
def test_random_manifolds_exact(dims, sigma, rng):
    table = manifold(dims, 3000, rng)
    queries = noisy(table, rng, 1500, sigma)
    grid = BucketGrid(table)
    rows, dist = grid.query(queries)
    assert_exact(table, queries, rows, dist)


@pytest.mark.parametrize("colour", [False, True], ids=["mono", "colour"])
@pytest.mark.parametrize("theta", [10, 45])
@pytest.mark.parametrize("m", [3, 5, 30])
def test_sphere_gauge_tables_exact(m, theta, colour, rng):
    table = sphere_table(m, theta, colour)
    queries = np.concatenate([noisy(table, rng, 1000, 0.005), noisy(table, rng, 500, 0.05)])
    grid = BucketGrid(table)
    rows, dist, stats = grid.query(queries, return_stats=True)
    assert_exact(table, queries, rows, dist)
    # The grid must do far less work than a linear scan on near queries.
    _, _, near = grid.query(queries[:1000], return_stats=True)
    assert near.tests < 0.02 * table.shape[0]


@pytest.mark.parametrize("m, colour", [(3, False), (3, True), (30, True)],
                         ids=["mono-runs", "colour-buckets", "colour-D90"])
def test_far_queries_exact(m, colour, rng):
    """Queries far off the manifold (outliers, other unit vectors, huge offsets).

    Covers both phase-1 scans (runs of cells for D <= 8, bucket by bucket
    above) and the coarse phase 2 behind them.
    """
    table = sphere_table(m, 45, colour)
    bands = 3 if colour else 1
    dims = table.shape[1]
    junk = np.abs(rng.normal(size=(300, bands, m)))
    junk /= np.linalg.norm(junk, axis=-1, keepdims=True)
    far = [junk.reshape(300, dims), rng.normal(0, 3, (100, dims)),
           table[:50] + 10.0, -table[:50]]
    queries = np.concatenate(far).astype(np.float32)
    rows, dist, stats = BucketGrid(table).query(queries, return_stats=True)
    assert_exact(table, queries, rows, dist)
    # Bounded cost: well under a linear scan even though every query is far.
    assert stats.tests < 0.3 * table.shape[0]


@pytest.mark.parametrize("m, theta", [(5, 10), (30, 10), (30, 45)])
def test_answers_do_not_depend_on_query_order(m, theta, rng):
    """A lookup adapts its work to the query before it (a neighbouring pixel
    in the pipeline's order): it computes the sketch at once when that query
    needed it. Answers must stay exact in any order, and equal to the answer
    of each query looked up alone."""
    table = sphere_table(m, theta, True)
    junk = np.abs(rng.normal(size=(200, 3, m)))
    junk /= np.linalg.norm(junk, axis=-1, keepdims=True)
    queries = np.concatenate([noisy(table, rng, 600, 0.005), noisy(table, rng, 300, 0.05),
                              junk.reshape(200, -1).astype(np.float32), table[:100]])
    grid = BucketGrid(table)
    alone = np.array([grid.query(q[None])[1][0] for q in queries[::11]])
    for order in (np.arange(len(queries)), np.arange(len(queries))[::-1],
                  rng.permutation(len(queries))):
        rows, dist = grid.query(queries[order])
        assert_exact(table, queries[order], rows, dist)
        back = np.empty_like(dist)
        back[order] = dist
        np.testing.assert_array_equal(back[::11], alone)


@pytest.mark.parametrize("dims, offset", [(3, 0.0), (12, 0.0), (90, 0.0), (90, 50.0)])
def test_sketch_bound_is_a_tight_lower_bound(dims, offset, rng):
    """The sketch test never exceeds the true squared distance (float64), even
    for queries far away or a table far from the origin (larger rounding), and
    it is tight enough to matter: most of the distance on near queries."""
    from colorps import _grid_kernels as kernels

    table = manifold(dims, 2000, rng) + np.float32(offset)
    queries = np.concatenate([noisy(table, rng, 200, 0.02),
                              noisy(table, rng, 50, 3.0)])
    grid = BucketGrid(table)
    sketch, points = grid._data.sketch, grid._data.entries.sketch
    entries = table[grid._data.entries.row].astype(np.float64)  # storage order
    low = np.zeros(kernels.SKETCH_LANES, dtype=np.float32)
    high = np.zeros(kernels.SKETCH_LANES, dtype=np.float32)
    ratios = []
    for q in queries:
        r2 = float(((q.astype(np.float64) - grid.center) ** 2).sum())
        q_norm2 = float((q.astype(np.float64) ** 2).sum())
        position = kernels.Position(0.0, 0.0, 0.0, r2, q_norm2)  # (u, v, h) unused
        kernels._query_sketch(q, position, sketch, low, high)
        true2 = ((entries - q.astype(np.float64)) ** 2).sum(axis=1)
        bound2 = np.array([kernels._sketch_gap2(low, high, points, points, e)
                           for e in range(entries.shape[0])])
        assert np.all(bound2 <= true2 * (1 + 1e-5) + 1e-12), (bound2 / true2).max()
        ratios.append(np.median(bound2 / true2))
    assert np.median(ratios[:200]) > 0.5


def test_tiny_tables(rng):
    for size in (1, 2):
        table = rng.normal(size=(size, 4)).astype(np.float32)
        queries = rng.normal(size=(200, 4)).astype(np.float32)
        for n in (None, 1, 5):
            rows, dist = BucketGrid(table, n).query(queries)
            assert_exact(table, queries, rows, dist)


def test_single_dimension(rng):
    table = rng.normal(size=(50, 1)).astype(np.float32)
    queries = rng.normal(size=(200, 1)).astype(np.float32)
    rows, dist = BucketGrid(table).query(queries)
    assert_exact(table, queries, rows, dist)


def test_duplicated_entries(rng):
    base = manifold(5, 200, rng)
    table = np.concatenate([base, base, base[:50]])
    queries = noisy(base, rng, 500, 0.01)
    rows, dist = BucketGrid(table).query(queries)
    assert_exact(table, queries, rows, dist)
    assert (rows < len(base)).all()  # of equal entries, the first
    # All-identical table: R is the epsilon of eq. 11, every entry ties.
    same = np.repeat(base[:1], 30, axis=0)
    rows, dist = BucketGrid(same).query(queries)
    assert_exact(same, queries, rows, dist)
    assert (rows == 0).all()


@pytest.mark.parametrize("dims", [4, 6, 18, 40])
def test_grid_and_brute_force_settle_near_ties_alike(dims, rng):
    """A mirror-symmetric table (a gauge lit symmetrically) and queries on its
    mirror: nearly every query has two entries at the same distance up to
    rounding. The grid and the brute force of few queries must pick the same
    one (a tiled run matches a group by one, the whole image by the other)."""
    from colorps.tables import BRUTE_FORCE_PIXELS, nearest

    half = dims // 2
    base = manifold(dims, 1500, rng)
    mirrored = np.concatenate([base[:, half:], base[:, :half]], axis=1)
    table = np.concatenate([base, mirrored])
    queries = noisy(table, rng, 400, 0.01)
    queries[:, half:] = queries[:, :half]  # on the mirror
    grid_rows, _ = BucketGrid(table).query(queries)
    brute_rows = np.concatenate([
        nearest(table, queries[a:a + BRUTE_FORCE_PIXELS - 1])[0]
        for a in range(0, len(queries), BRUTE_FORCE_PIXELS - 1)])
    assert nearest(table, queries[:BRUTE_FORCE_PIXELS - 1])[3] is None  # brute force
    np.testing.assert_array_equal(grid_rows, brute_rows)


def test_queries_on_cell_borders(rng):
    table = sphere_table(5, 45, False)
    grid = BucketGrid(table, 40)
    u, v = grid.axes
    edges = -grid.half_width + grid.cell_side * np.arange(41)
    a, b = np.meshgrid(edges, edges[::3], indexing="ij")
    queries = (grid.center + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v).astype(np.float32)
    queries = np.concatenate([queries, table[::17]])  # entries themselves
    rows, dist = grid.query(queries)
    assert_exact(table, queries, rows, dist)
    np.testing.assert_array_equal(dist[-len(table[::17]):], 0.0)


def test_n1_is_linear_scan(rng):
    table = sphere_table(3, 10, False)
    queries = noisy(table, rng, 300, 0.01)
    rows, dist, stats = BucketGrid(table, 1).query(queries, return_stats=True)
    assert_exact(table, queries, rows, dist)
    assert stats.buckets == 1
    assert stats.tests <= table.shape[0]


def test_stats_and_threads(rng):
    table = manifold(3, 2000, rng)
    queries = noisy(table, rng, 2000, 0.01)
    grid = BucketGrid(table)
    r1, d1, s1 = grid.query(queries, threads=1, return_stats=True)
    r2, d2, s2 = grid.query(queries, threads=2, return_stats=True)
    np.testing.assert_array_equal(d1, d2)
    assert s1.buckets == s2.buckets > 0 and s1.tests == s2.tests > 0
    assert s1.buckets_per_query.shape == (2000,)
    assert grid.bucket_counts.sum() == 2000 and grid.n == round(2 * np.sqrt(2000))


def test_auto_n_picks_a_candidate_and_stays_exact(rng):
    table = manifold(10, 2500, rng)
    queries = noisy(table, rng, 1000, 0.05)
    grid = BucketGrid(table, "auto", sample=queries)
    base = 2 * np.sqrt(2500)
    assert grid.n in {round(base * f) for f in (0.25, 0.5, 1, 2)}
    rows, dist = grid.query(queries)
    assert_exact(table, queries, rows, dist)
    assert BucketGrid(table, "auto").n == round(base)  # no sample: default N


@pytest.mark.parametrize("bad, message", [
    (np.zeros((0, 3)), "empty"),
    (np.zeros(5), "2-D"),
    (np.zeros((2, 2, 2)), "2-D"),
    (np.array([[0.0, np.nan]]), "NaN or Inf"),
    (np.array([[0.0, np.inf]]), "NaN or Inf"),
    (np.array([["a", "b"]]), "real numbers"),
])
def test_bad_tables(bad, message):
    with pytest.raises(InputError, match=message):
        BucketGrid(bad)


@pytest.mark.parametrize("n", [0, -3, 2.5, "big", True])
def test_bad_n(n):
    with pytest.raises(InputError, match="n:"):
        BucketGrid(np.ones((4, 3)), n)


def test_bad_queries(rng):
    grid = BucketGrid(rng.normal(size=(20, 3)))
    with pytest.raises(InputError, match="dimensions"):
        grid.query(np.ones((2, 4)))
    with pytest.raises(InputError, match="NaN or Inf"):
        grid.query(np.array([[0, 0, np.nan]]))
    with pytest.raises(InputError, match="2-D"):
        grid.query(np.ones(3))
    with pytest.raises(InputError, match="threads"):
        grid.query(np.ones((1, 3)), threads=0)


finite = st.floats(-4, 4, allow_nan=False, width=32)


@settings(max_examples=60, deadline=None)
@given(table=arrays(np.float32, st.tuples(st.integers(1, 60), st.just(4)), elements=finite),
       queries=arrays(np.float32, st.tuples(st.integers(1, 20), st.just(4)), elements=finite),
       n=st.one_of(st.none(), st.integers(1, 12)))
def test_property_exact(table, queries, n):
    rows, dist = BucketGrid(table, n).query(queries)
    assert_exact(table, queries, rows, dist)


def test_reference_is_brute_force():
    """The reference itself: a hand-checked case."""
    table = np.array([[0, 0], [1, 0], [0, 2]], dtype=np.float32)
    np.testing.assert_allclose(nearest_distances(table, [[0.9, 0.1], [0, 1.2]]),
                               [np.hypot(0.1, 0.1), 0.8], rtol=1e-12)
