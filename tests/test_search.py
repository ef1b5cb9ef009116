"""Tests of ucad_cl.search against NumPy float64 references (independent: host, float64)."""
from __future__ import annotations

import numpy as np
import pytest

from ucad_cl.search import FeatureIndex, search

pytestmark = pytest.mark.every_device      # tests/conftest.py: UCAD_TEST_DEVICES


def ref_sq(q: np.ndarray, db: np.ndarray) -> np.ndarray:
    """(Q, N) float64 squared distances by direct difference."""
    q64, db64 = q.astype(np.float64), db.astype(np.float64)
    return np.stack([((db64 - v) ** 2).sum(1) for v in q64])


def ref_rank(d64: np.ndarray, k: int) -> np.ndarray:
    """Rows ordered by (distance, row): the documented tie rule."""
    return np.argsort(d64, axis=1, kind="stable")[:, :k]


def hog_like(n: int, dim: int, seed: int) -> np.ndarray:
    """Non-negative, L2-normalised, clustered rows (like HOG view features)."""
    rng = np.random.default_rng(seed)
    centres = np.maximum(rng.standard_normal((max(1, n // 24), dim)), 0)
    x = centres[rng.integers(0, len(centres), n)] + 0.25 * rng.standard_normal((n, dim))
    x = np.maximum(x, 0) + 1e-3
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def recall(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.mean([len(set(a) & set(b)) / len(b) for a, b in zip(got, want)]))


def test_f32_matches_float64_ranking(runtime):
    rng = np.random.default_rng(0)
    db = rng.standard_normal((3001, 100)).astype(np.float32)
    q = rng.standard_normal((17, 100)).astype(np.float32)
    d64 = ref_sq(q, db)
    want = ref_rank(d64, 10)
    srt = np.sort(d64, axis=1)[:, :11]
    assert np.diff(srt, axis=1).min() > 1e-3      # no near-ties: the ranking is unambiguous
    idx, dist = search(q, db, 10, runtime=runtime)
    assert idx.dtype == np.int64 and dist.dtype == np.float32 and idx.shape == (17, 10)
    np.testing.assert_array_equal(idx, want)
    np.testing.assert_allclose(dist, np.take_along_axis(d64, want, 1), rtol=2e-6)


def test_identical_rows_tie_to_lower_index(runtime):
    rng = np.random.default_rng(1)
    db = rng.standard_normal((200, 40)).astype(np.float32)
    v = db[150].copy()
    db[[7, 33, 150]] = v
    idx, dist = search(v[None], db, 3, runtime=runtime)
    np.testing.assert_array_equal(idx[0], [7, 33, 150])
    assert (dist == 0).all()
    # query between two identical rows and one nearer row: ties keep lower index after it
    db[90] = v + np.float32(1e-3)
    idx, _ = search((v + np.float32(6e-4))[None], db, 4, runtime=runtime)
    np.testing.assert_array_equal(idx[0], [90, 7, 33, 150])


def test_mass_ties_ordered_by_row(runtime):
    """Small-integer features: distances are exact integers with thousands of exact ties, spread
    over every row chunk and merge; the order must be (distance, row) exactly."""
    rng = np.random.default_rng(12)
    db = rng.integers(0, 3, (20_000, 9)).astype(np.float32)
    q = rng.integers(0, 3, (6, 9)).astype(np.float32)
    d64 = ref_sq(q, db)
    for k in (1, 17, 64):
        idx, dist = FeatureIndex(db, runtime=runtime).search(q, k)
        np.testing.assert_array_equal(idx, ref_rank(d64, k))
        np.testing.assert_array_equal(dist, np.take_along_axis(d64, idx, 1))
    idx, _ = FeatureIndex(db, runtime=runtime).search(q[2], 64)                    # Q = 1 path (QB = 1)
    np.testing.assert_array_equal(idx[0], ref_rank(d64, 64)[2])


def test_near_duplicates_no_cancellation(runtime):
    """|x| ~ 1e3, differences ~1e-2: |q|^2 - 2 q.x + |x|^2 in float32 would misorder these."""
    dim = 64
    base = np.full(dim, 1000.0, np.float32)
    offsets = np.array([5, 3, 8, 1, 6, 2, 7, 4], np.float32) * np.float32(1 / 128)
    db = np.repeat(base[None], len(offsets), 0)
    db[np.arange(len(offsets)), np.arange(len(offsets))] += offsets
    idx, dist = search(base[None], db, len(offsets), runtime=runtime)
    np.testing.assert_array_equal(idx[0], np.argsort(offsets, kind="stable"))
    np.testing.assert_array_equal(dist[0], np.sort(offsets) ** 2)   # exact: dyadic values
    # and the expansion really does fail here (so the test can tell the two apart)
    q = base.astype(np.float32)
    expand = (q @ q) - 2 * (db @ q) + np.einsum("ij,ij->i", db, db)
    assert not np.array_equal(np.argsort(expand, kind="stable"), np.argsort(offsets))


def test_all_zero_rows_and_queries(runtime):
    rng = np.random.default_rng(2)
    zeros = np.zeros((50, 24), np.float32)
    idx, dist = search(np.zeros((2, 24), np.float32), zeros, 5, runtime=runtime)
    np.testing.assert_array_equal(idx, [[0, 1, 2, 3, 4]] * 2)
    assert (dist == 0).all()
    db = rng.standard_normal((500, 24)).astype(np.float32)
    db[[3, 400]] = 0
    idx, dist = search(np.zeros(24, np.float32), db, 4, runtime=runtime)          # 1-D query = Q of 1
    np.testing.assert_array_equal(idx[0], ref_rank(ref_sq(np.zeros((1, 24)), db), 4)[0])
    assert list(idx[0][:2]) == [3, 400] and (dist[0][:2] == 0).all()


def test_huge_magnitudes_same_ranking(runtime):
    rng = np.random.default_rng(3)
    db = rng.standard_normal((2000, 20)).astype(np.float32)
    q = rng.standard_normal((5, 20)).astype(np.float32)
    want = ref_rank(ref_sq(q, db), 8)
    for scale in (1e18, 3e-18):
        idx, dist = search(q * np.float32(scale), db * np.float32(scale), 8, runtime=runtime)
        np.testing.assert_array_equal(idx, want)
        assert np.isfinite(dist).all() and (dist > 0).all()
        ref = ref_sq(q * np.float32(scale), db * np.float32(scale))
        np.testing.assert_allclose(dist, np.take_along_axis(ref, want, 1), rtol=1e-5)


def test_bad_input_errors(runtime):
    rng = np.random.default_rng(4)
    db = rng.standard_normal((30, 10)).astype(np.float32)
    index = FeatureIndex(db, runtime=runtime)
    q = rng.standard_normal((3, 10)).astype(np.float32)
    q[1, 4] = np.nan
    with pytest.raises(ValueError, match="query 1 contains NaN"):
        index.search(q, 2)
    with pytest.raises(ValueError, match=r"k=31 out of range.*N=30"):
        index.search(q[:1], 31)
    with pytest.raises(ValueError, match="k=0 out of range"):
        index.search(q[:1], 0)
    with pytest.raises(ValueError, match="queries have 11 features, the database has 10"):
        index.search(np.zeros((1, 11), np.float32), 1)
    with pytest.raises(ValueError, match="database is empty"):
        FeatureIndex(np.zeros((0, 10), np.float32), runtime=runtime)
    bad = db.copy()
    bad[5, 0] = np.inf
    with pytest.raises(ValueError, match="database row 5 contains inf"):
        FeatureIndex(bad, runtime=runtime)
    with pytest.raises(ValueError, match="unknown search mode"):
        FeatureIndex(db, mode="int8", runtime=runtime)
    with pytest.raises(ValueError, match="2-D"):
        FeatureIndex(db[0], runtime=runtime)
    with pytest.raises(ValueError, match="overflow"):
        index.search(np.full((1, 10), 1e30, np.float32), 1)


def test_odd_dim_single_query_large_n_and_ids(runtime):
    rng = np.random.default_rng(5)
    db = rng.standard_normal((100_003, 37)).astype(np.float32)
    q = rng.standard_normal(37).astype(np.float32)
    ids = np.arange(100_003, dtype=np.int64) * 10 + 7
    index = FeatureIndex(db, ids=ids, runtime=runtime)
    idx, dist = index.search(q, 64)
    d64 = ref_sq(q[None], db)
    want = ref_rank(d64, 64)
    np.testing.assert_array_equal(idx, ids[want])
    np.testing.assert_allclose(dist, np.take_along_axis(d64, want, 1), rtol=2e-6)


def test_deterministic_and_batch_independent(runtime):
    db = hog_like(5000, 96, 6)
    q = hog_like(40, 96, 7)
    index = FeatureIndex(db, runtime=runtime)
    a = index.search(q, 12)
    b = index.search(q, 12)
    c = [index.search(q[i], 12) for i in (0, 13, 39)]      # same query alone
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1].tobytes() == b[1].tobytes()
    for i, (ci, cd) in zip((0, 13, 39), c):
        np.testing.assert_array_equal(ci[0], a[0][i])
        assert cd[0].tobytes() == a[1][i].tobytes()


def test_f16_is_exact_search_on_half_rounded_database(runtime):
    db = hog_like(4000, 128, 8)
    q = hog_like(30, 128, 9)
    e = int(np.frexp(np.abs(db).max())[1])
    db_half = np.ldexp(np.ldexp(db, -e).astype(np.float16).astype(np.float64), e)
    idx, dist = search(q, db, 10, mode="f16", runtime=runtime)
    d64 = ref_sq(q, db_half)
    top = np.take_along_axis(d64, idx, 1)
    best = d64.min(1)
    assert np.all(top[:, 0] <= best * (1 + 1e-5) + 1e-9)   # top-1 is the half-DB optimum
    np.testing.assert_allclose(dist, top, rtol=1e-5, atol=1e-7)
    exact, _ = search(q, db, 10, runtime=runtime)
    assert recall(idx[:, :1], exact[:, :1]) >= 0.95
    assert recall(idx, exact) >= 0.95


def test_pca_against_numpy_projection_and_rerank(runtime):
    db = hog_like(3000, 64, 10)
    q = hog_like(25, 64, 11)
    exact, exact_d = search(q, db, 10, runtime=runtime)
    # reduced-space search equals exact search on an independent SVD projection
    x64 = db.astype(np.float64)
    mean = x64.mean(0)
    _, _, vt = np.linalg.svd(x64 - mean, full_matrices=False)
    proj = lambda a: (a.astype(np.float64) - mean) @ vt[:24].T
    d_red = ref_sq(proj(q), proj(db))
    idx, dist = search(q, db, 10, mode="pca", pca_dims=24, runtime=runtime)
    again = search(q, db, 10, mode="pca", pca_dims=24, runtime=runtime)             # fit + search deterministic
    np.testing.assert_array_equal(again[0], idx)
    assert again[1].tobytes() == dist.tobytes()
    np.testing.assert_allclose(dist, np.take_along_axis(d_red, idx, 1), rtol=1e-4, atol=1e-6)
    assert recall(idx, ref_rank(d_red, 10)) >= 0.98
    # with a rerank of the top 64 the result is at least as good, and exact at full rank
    rr, rr_d = search(q, db, 10, mode="pca", pca_dims=24, rerank=64, runtime=runtime)
    assert recall(rr, exact) > recall(idx, exact) + 0.2 and recall(rr[:, :1], exact[:, :1]) >= 0.8
    np.testing.assert_allclose(rr_d, np.take_along_axis(ref_sq(q, db), rr, 1), rtol=2e-6)
    assert np.all(np.diff(rr_d, axis=1) >= 0)
    full, full_d = search(q, db, 10, mode="pca", pca_dims=64, rerank=20, runtime=runtime)
    np.testing.assert_array_equal(full, exact)
    assert full_d.tobytes() == exact_d.tobytes()
    with pytest.raises(ValueError, match="rerank must be"):
        FeatureIndex(db[:20], mode="pca", pca_dims=8, rerank=21, runtime=runtime)
    with pytest.raises(ValueError, match="pca_dims"):
        FeatureIndex(db, mode="pca", pca_dims=65, runtime=runtime)
    with pytest.raises(ValueError, match="rerank=5 is smaller than k=10"):
        search(q, db, 10, mode="pca", pca_dims=24, rerank=5, runtime=runtime)


def test_pca_rerank_expansion_preselection_near_duplicates(runtime):
    """Batches of >= 4 queries preselect re-rank candidates by the float32 expansion
    (sq_l2_dot_tile). Its cancellation must not lose the exact answer: clusters of 40
    near-duplicate rows (differences 1e-5, far below the expansion's error on these norms) around
    each query's true neighbour still fit in rerank=64, so top-k equals the exact f32 scan, rows
    and bytes of the distances; a single query (direct-difference path) agrees with the batch."""
    rng = np.random.default_rng(21)
    db = hog_like(4000, 96, 20)
    q = db[rng.choice(4000, 12, replace=False)] + 0.02 * rng.standard_normal((12, 96))
    q = (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)
    near = np.argsort(ref_sq(q, db), axis=1)[:, 0]
    dup = db[np.repeat(near, 40)] + 1e-5 * rng.standard_normal((len(q) * 40, 96)).astype(np.float32)
    db = np.concatenate([db, dup.astype(np.float32)])
    exact, exact_d = search(q, db, 10, runtime=runtime)
    assert ref_rank(ref_sq(q, db), 1)[:, 0].tolist() == exact[:, 0].tolist()
    index = FeatureIndex(db, mode="pca", pca_dims=32, rerank=64, runtime=runtime)
    idx, dist = index.search(q, 10)
    np.testing.assert_array_equal(idx, exact)
    assert dist.tobytes() == exact_d.tobytes()
    one, one_d = index.search(q[3], 10)
    np.testing.assert_array_equal(one[0], idx[3])
    assert one_d[0].tobytes() == dist[3].tobytes()
