"""Slow, obviously correct references the fast code is compared with."""

import numpy as np


def nearest_distances(table, queries, chunk_bytes=64_000_000):
    """Exact nearest distance of every query: float64, direct vector differences."""
    t = np.asarray(table, dtype=np.float64)
    q_all = np.asarray(queries, dtype=np.float64)
    out = np.empty(q_all.shape[0])
    chunk = max(1, chunk_bytes // (8 * t.size))
    for a in range(0, q_all.shape[0], chunk):
        q = q_all[a:a + chunk]
        d2 = ((q[:, None, :] - t[None, :, :]) ** 2).sum(axis=-1)
        out[a:a + chunk] = np.sqrt(d2.min(axis=1))
    return out


def assert_exact(table, queries, rows, distances):
    """The returned rows are brute-force nearest (up to float32 near-ties)."""
    table = np.asarray(table, dtype=np.float32)
    queries = np.asarray(queries, dtype=np.float32)
    ref = nearest_distances(table, queries)
    got = np.sqrt(((table[rows].astype(np.float64) - queries.astype(np.float64)) ** 2)
                  .sum(axis=1))
    wrong = got > ref * (1 + 1e-5) + 1e-6
    assert not wrong.any(), (
        f"{wrong.sum()} of {len(rows)} lookups not nearest; worst excess "
        f"{(got - ref).max():.3g}")
    np.testing.assert_allclose(distances, got, rtol=1e-4, atol=1e-5)
