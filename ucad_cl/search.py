"""Exact k-nearest-neighbour search of view features by squared L2 distance (OpenCL).

UrbanCAD matches a reference image's feature vector against every rendered view's feature
vector. A :class:`FeatureIndex` keeps the (N, D) database resident on the device (uploaded once)
and answers ``search(queries (Q, D), k) -> (indices (Q, k) int64, sq_dists (Q, k) float32)``,
nearest first.

Conventions
* Distance: squared Euclidean, sum_j (q_j - x_j)^2, computed on the device by direct difference
  in float32 with a fixed summation order (see ``ucad_cl/kernels/search.cl`` for why not the
  |q|^2 - 2 q.x + |x|^2 expansion: it cancels catastrophically for near-identical vectors).
* Tie rule: results are ordered by (distance, database row) lexicographically, i.e. equal
  float32 distances -> lower database row (position in the array given to the index, not the
  optional id) first. The result never depends on work-item order.
* Scaling: the database is multiplied by an exact power of two 2^-e chosen so that its largest
  magnitude lies in [0.5, 1), and queries by the same factor. Power-of-two scaling is exact (barring
  underflow of components 2^-149 below the maximum), so rankings equal those on the unscaled data
  while 1e18-sized features cannot overflow. Returned ``sq_dists`` are in the caller's units
  (multiplied back by 2^2e in float64), saturated at float32's largest finite value.
* Modes: ``"f32"`` exact; ``"f16"`` database stored as IEEE half (round to nearest even, after
  scaling), query and accumulation float32; ``"pca"`` database and queries projected on the top
  ``pca_dims`` principal axes (fitted in float64 on the host, deterministic signs) and searched
  exactly in float32 in that space; with ``rerank=R`` the R best reduced-space candidates are
  re-ranked by exact float32 distances in the full space (then sq_dists are full-space distances,
  otherwise reduced-space ones). With a re-rank and Q >= DOT_QB queries, the candidates are chosen
  by the expansion |q|^2 + |x|^2 - 2 q.x in float32 (``sq_l2_dot_tile``, half the arithmetic of
  direct differences): its cancellation error (~1e-7 of the squared norms of the reduced,
  centred vectors) can only swap candidates within that error of the R-th; the re-rank is exact.
* k: 1 <= k <= min(N, 64); k > N is an error (not clipped). NaN/inf anywhere is an error.

Catalogue search (``search_catalog``, ``search_catalog_batch``: the pose search's and the fit's
retrieval over the stored views of many meshes): each row carries its (mesh, view); the
ranking is ``rank_features``' exact float64 distance of unit rows, over every row up to
``EXACT_ROWS`` rows, else over the ``PRESELECT`` rows this module's float32 search keeps; ties:
the lower row.

Cost (PoCL, 2 cores, 100 queries x 72,000 x 512, bench/search.py): f32 ~25-50 ms per batch, about
2-5x NumPy's sgemm scan and 7-12x faiss IndexFlatL2 with the same top-1. f16 halves the resident
database but is ~1.3x slower than f32 here (half -> float conversion in every work-item); pca
d=64/128 is 1.5-2.5x faster, with top-1 recall 0.51/0.64 alone and 1.00 with rerank=32 on
HOG-like features. Catalogue search (bench/pose.py --catalog: 168 queries x 72,000 x 1,764 HOG,
pca 128 + rerank 64): CPU s per batch 0.12-0.19 vs 0.25-0.28 before the expansion preselection
and fewer top-k chunks, where the projection of the queries is ~7 ms, the preselection ~100 ms,
top-k ~20 ms and the re-rank gather ~15 ms. Device memory: database + one (Q batch x N) float32
distance matrix.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ucad_catalog.searchindex import fit_pca

from .abi import DIST_PARAMS, GATHER_PARAMS, K_MAX, MERGE_PARAMS, TOPK_PARAMS
from .features import unit_rows
from .runtime import Runtime, get_runtime

MODES = ("f32", "f16", "pca")
EXACT_ROWS = 50_000         # search_catalog ranks up to this many rows exactly on the host
RANK_ROWS = 128             # rank_features normalises this many rows at a time (cache-sized:
#                             2048 x 1764 rows 33 -> 13 ms on a Zen 4; the same bits)
PRESELECT = 64              # rows taken from the OpenCL search for the exact re-rank (k <= 64)
RERANK_BATCH = 32           # queries re-ranked together (bounds the float64 scratch to ~30 MB)
# Register block (queries x rows) of sq_l2_tile. PoCL, 2 cores, 100 x 72,000 x 512, quietest
# runs: 4x4 22 ms, 6x4 22, 2x8 22-27, 4x8 35, 8x4 52, 8x2 63. Batches of 1-3 queries use QB = 1
# (memory-bound: 8 ms vs 15 ms with zero-padded QB = 4).
QB, RB = 4, 4
# Register block of sq_l2_dot_tile (re-rank candidates in pca mode, float8 accumulators: 8 of
# the 16 AVX2 registers). Kernel CPU ms, 168 x 72,000 x 128, PoCL 3.1 on 2 loaded Zen 3 cores:
# 4x2 98, 2x4 107, 4x4 114, 8x2 124; sq_l2_tile (direct differences, 4x4) 139; NumPy's sgemm
# for the same product 70-77 (the machine, not the kernel, is the limit).
DOT_QB, DOT_RB = 4, 2
# Local size: query blocks per work-group = the largest divisor of their count <= LQ_MAX
# (25 and 1 measured equal; a bounded set of local sizes bounds PoCL's per-size compiles).
LQ_MAX = 16
ONE_ITEM = (1, 1)       # local size of topk_rows and sq_l2_gather (PoCL's default: 2x slower)
DIST_BUDGET = 1 << 26   # floats in one (Q batch x N) distance matrix (256 MiB)
UPLOAD_ROWS = 8192      # rows per host->device slice and per PCA chunk
# Target work-items of topk_rows (query x row chunk). Fewer, longer chunks insert less
# (about k ln(chunk / k) insertions per chunk): 168 queries x 72,000 rows, k = 64, CPU s of the
# whole pca search 0.12-0.14 with 64 vs 0.14-0.16 with 512 (PoCL 3.1, 2 loaded Zen 3 cores).
TOPK_ITEMS = 64



def search(queries: np.ndarray, db: np.ndarray, k: int, mode: str = "f32",
           **options) -> tuple[np.ndarray, np.ndarray]:
    """One-shot search: build a :class:`FeatureIndex` over ``db`` and query it."""
    return FeatureIndex(db, mode=mode, **options).search(queries, k)


class FeatureIndex:
    """Brute-force L2 index over an (N, D) float32 database, resident on the OpenCL device.

    ids: optional (N,) integers returned instead of row positions (ties still go by row).
    pca_dims: reduced dimension for mode "pca"; rerank: exact re-rank of that many candidates
    (0 = off, else k <= rerank <= 64).
    """

    def __init__(self, db: np.ndarray, ids: np.ndarray | None = None, mode: str = "f32",
                 pca_dims: int = 64, rerank: int = 0, runtime: Runtime | None = None):
        if mode not in MODES:
            raise ValueError(f"unknown search mode {mode!r}; expected one of {MODES}")
        x = _as_matrix(db, "database")
        if x.shape[0] == 0:
            raise ValueError("database is empty (0 rows): nothing to search")
        _check_finite(x, "database row")
        self.n_rows, self.dim = x.shape
        self.mode = mode
        self.ids = None
        if ids is not None:
            self.ids = np.asarray(ids)
            if self.ids.shape != (self.n_rows,) or self.ids.dtype.kind not in "iu":
                raise ValueError(f"ids must be ({self.n_rows},) integers, got "
                                 f"{self.ids.shape} {self.ids.dtype}")
            self.ids = self.ids.astype(np.int64)
        self.rerank = int(rerank)
        if mode == "pca":
            if not 1 <= pca_dims <= self.dim:
                raise ValueError(f"pca_dims must be in 1..{self.dim}, got {pca_dims}")
            if self.rerank and not 1 <= self.rerank <= min(K_MAX, self.n_rows):
                raise ValueError(f"rerank must be 0 or in 1..min(N={self.n_rows}, {K_MAX}), "
                                 f"got {rerank}")
            self.pca_mean, self.pca_axes = fit_pca(x, pca_dims, UPLOAD_ROWS)
            stored = np.concatenate([(x[i:i + UPLOAD_ROWS].astype(np.float64) - self.pca_mean)
                                     @ self.pca_axes for i in range(0, self.n_rows, UPLOAD_ROWS)])
        else:
            self.rerank = 0
            stored = x
        self.rt = runtime or get_runtime()
        # device steps use the runtime's kernels and scratch buffers, shared by every index on
        # it: calls are serialised per runtime
        self._lock = self.rt.exclusive
        self.exp = _scale_exponent(stored)
        self.dim_pad = _round_up(stored.shape[1], 16)
        self.rows_pad = _round_up(self.n_rows, 16)      # multiple of RB and of 16
        store_dt = np.float16 if mode == "f16" else np.float32
        self.d_db = self._upload(stored, self.exp, self.rows_pad, self.dim_pad, store_dt)
        if self.rerank:
            # squared norms of the stored (scaled, float32) reduced rows, for the expansion
            # preselection (sq_l2_dot_tile)
            norm2 = np.zeros(self.rows_pad, np.float32)
            for r0 in range(0, self.n_rows, UPLOAD_ROWS):
                part = _pack(stored[r0:r0 + UPLOAD_ROWS], self.exp, len(stored[r0:r0 + UPLOAD_ROWS]),
                             self.dim_pad, np.float32).astype(np.float64)
                norm2[r0:r0 + len(part)] = np.einsum("ij,ij->i", part, part)
            self.d_norm2 = self._upload(norm2[:, None], 0, self.rows_pad, 1, np.float32)
            self.full_exp = _scale_exponent(x)
            self.full_dim_pad = _round_up(self.dim, 16)
            self.d_full = self._upload(x, self.full_exp, self.n_rows, self.full_dim_pad, np.float32)

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """k nearest rows per query: (indices (Q, k) int64, sq_dists (Q, k) float32).

        A 1-D query is treated as Q = 1. Ties: lower database row first. Calls on one index
        are serialised (it reuses its device scratch buffers).
        """
        q = np.asarray(queries)
        if q.ndim == 1:
            q = q[None, :]
        q = _as_matrix(q, "queries")
        if q.shape[1] != self.dim:
            raise ValueError(f"queries have {q.shape[1]} features, the database has {self.dim}")
        _check_finite(q, "query")
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
            raise TypeError(f"k must be an integer, got {k!r}")
        k = int(k)
        if not 1 <= k <= min(self.n_rows, K_MAX):
            raise ValueError(f"k={k} out of range: need 1 <= k <= min(N={self.n_rows}, {K_MAX})")
        if self.rerank and self.rerank < k:
            raise ValueError(f"rerank={self.rerank} is smaller than k={k}")
        with self._lock:
            return self._search(q, k)

    def _search(self, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        nq = q.shape[0]
        rows = np.empty((nq, k), np.int64)
        dist = np.empty((nq, k), np.float32)
        if nq == 0:
            return rows, dist
        qs = (q.astype(np.float64) - self.pca_mean) @ self.pca_axes if self.mode == "pca" else q
        kk = self.rerank or k
        batch = max(QB, min(256, DIST_BUDGET // self.rows_pad) // QB * QB)
        for q0 in range(0, nq, batch):
            q1 = min(nq, q0 + batch)
            r, d = self._knn(qs[q0:q1], kk)
            if self.rerank:
                r, d = self._rerank(q[q0:q1], r, k)
                exp = self.full_exp
            else:
                exp = self.exp
            rows[q0:q1] = r
            dist[q0:q1] = _unscale_dists(d, exp)
        return (self.ids[rows] if self.ids is not None else rows), dist

    def _upload(self, x: np.ndarray, exp: int, rows: int, cols: int, dtype):
        """Device copy of x * 2^-exp, zero-padded to (rows, cols), sent in slices (low peak RSS)."""
        import pyopencl as cl

        row_bytes = cols * np.dtype(dtype).itemsize
        buf = cl.Buffer(self.rt.ctx, cl.mem_flags.READ_ONLY, rows * row_bytes)
        for r0 in range(0, rows, UPLOAD_ROWS):
            part = _pack(x[r0:r0 + UPLOAD_ROWS], exp, min(UPLOAD_ROWS, rows - r0), cols, dtype)
            cl.enqueue_copy(self.rt.queue, buf, part, dst_offset=r0 * row_bytes)
        self.rt.queue.finish()
        return buf

    def _tile_kernel(self, qb: int):
        """sq_l2_tile built for a QB x RB block and this index's storage type (the runtime
        caches it)."""
        opts = (f"-DQB={qb}", f"-DRB={RB}") + (("-DDB_HALF",) if self.mode == "f16" else ())
        return self.rt.kernel("search", "sq_l2_tile", opts)

    def _scratch(self, name: str, nbytes: int):
        """The runtime's scratch buffer ``search.<name>`` (reused across calls: fresh pages cost
        PoCL page faults)."""
        return self.rt.scratch(f"search.{name}", nbytes)

    # -- device steps ------------------------------------------------------------------------
    def _knn(self, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-k (rows, scaled sq dists) of a query batch against the resident database."""
        import pyopencl as cl

        ctx, queue = self.rt.ctx, self.rt.queue
        nq = q.shape[0]
        qb = QB if nq >= QB else 1
        q_pad = _round_up(nq, qb)
        q_blocks = q_pad // qb
        lq = max(d for d in range(1, min(LQ_MAX, q_blocks) + 1) if q_blocks % d == 0)
        qbuf = _pack(q, self.exp, q_pad, self.dim_pad, np.float32)
        _check_query_range(qbuf, self.dim_pad)
        mf = cl.mem_flags
        d_q = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=qbuf)
        d_dist = self._scratch("dist", 4 * _round_up(nq, max(QB, DOT_QB)) * self.rows_pad)
        prm = np.array([(nq, self.n_rows, self.dim_pad // 16, q_pad, self.rows_pad)], DIST_PARAMS)
        if self.rerank and nq >= DOT_QB:
            # candidates for the exact re-rank: expansion distances (one fma per term)
            q_pad = _round_up(nq, DOT_QB)
            qbuf = _pack(q, self.exp, q_pad, self.dim_pad, np.float32)
            qn2 = np.einsum("ij,ij->i", qbuf.astype(np.float64), qbuf.astype(np.float64))
            d_q = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=qbuf)
            d_qn2 = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=qn2.astype(np.float32))
            q_blocks = q_pad // DOT_QB
            lq = max(d for d in range(1, min(LQ_MAX, q_blocks) + 1) if q_blocks % d == 0)
            prm["q_stride"] = q_pad
            kernel = self.rt.kernel("search", "sq_l2_dot_tile", (f"-DDQB={DOT_QB}", f"-DDRB={DOT_RB}"))
            _launch(queue, kernel, (q_blocks, self.rows_pad // DOT_RB), (lq, 1),
                    prm, d_q, self.d_db, d_qn2, self.d_norm2, d_dist)
        else:
            _launch(queue, self._tile_kernel(qb), (q_blocks, self.rows_pad // RB), (lq, 1),
                    prm, d_q, self.d_db, d_dist)
        # Row chunks per query: enough work-items for every core, each chunk at least k rows.
        n_chunks = max(1, min(-(-TOPK_ITEMS // nq), self.n_rows // max(k, 16)))
        chunk = _round_up(-(-self.n_rows // n_chunks), 16)
        n_chunks = -(-self.n_rows // chunk)
        d_cd = self._scratch("cand_d", 4 * nq * n_chunks * k)
        d_cr = self._scratch("cand_r", 4 * nq * n_chunks * k)
        prm = np.array([(nq, self.n_rows, self.rows_pad, chunk, n_chunks, k)], TOPK_PARAMS)
        _launch(queue, self.rt.kernel("search", "topk_rows"), (n_chunks, nq), ONE_ITEM, prm, d_dist, d_cd,
                d_cr)
        return self._merge(d_cd, d_cr, nq, n_chunks * k, k)

    def _merge(self, d_cd, d_cr, nq: int, n_cand: int, k: int):
        import pyopencl as cl

        queue = self.rt.queue
        d_od = self._scratch("out_d", 4 * nq * k)
        d_or = self._scratch("out_r", 4 * nq * k)
        prm = np.array([(nq, n_cand, k)], MERGE_PARAMS)
        _launch(queue, self.rt.kernel("search", "topk_merge"), (nq,), (1,), prm, d_cd, d_cr, d_od, d_or)
        out_d = np.empty((nq, k), np.float32)
        out_r = np.empty((nq, k), np.int32)
        cl.enqueue_copy(queue, out_d, d_od)
        cl.enqueue_copy(queue, out_r, d_or).wait()
        return out_r.astype(np.int64), out_d

    def _rerank(self, q: np.ndarray, cand: np.ndarray, k: int):
        """Exact full-space distances of the reduced-space candidates, then top-k of those."""
        import pyopencl as cl

        ctx, queue = self.rt.ctx, self.rt.queue
        nq, n_cand = cand.shape
        qbuf = _pack(q, self.full_exp, nq, self.full_dim_pad, np.float32)
        _check_query_range(qbuf, self.full_dim_pad)
        mf = cl.mem_flags
        d_q = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=qbuf)
        d_rows = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR,
                           hostbuf=np.ascontiguousarray(cand, np.int32))
        d_cd = self._scratch("gather_d", 4 * nq * n_cand)
        prm = np.array([(nq, self.full_dim_pad // 16, n_cand)], GATHER_PARAMS)
        _launch(queue, self.rt.kernel("search", "sq_l2_gather"), (n_cand, nq), ONE_ITEM, prm, d_q,
                self.d_full, d_rows, d_cd)
        return self._merge(d_cd, d_rows, nq, n_cand, k)


# -- host helpers ----------------------------------------------------------------------------
def _launch(queue, kernel, gsize, lsize, *args):
    import pyopencl as cl

    kernel.set_args(*args)
    cl.enqueue_nd_range_kernel(queue, kernel, gsize, lsize)


def _round_up(n: int, m: int) -> int:
    return -(-n // m) * m


def _as_matrix(a, what: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"{what} must be a 2-D (rows, features) array, got shape {a.shape}")
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{what} must be numeric, got dtype {a.dtype}")
    if a.shape[1] == 0:
        raise ValueError(f"{what} has 0 features")
    if a.dtype.kind == "f" and a.dtype.itemsize > 4:
        big = np.abs(a[np.isfinite(a)]).max(initial=0.0)
        if big > np.finfo(np.float32).max:
            raise ValueError(f"{what} has magnitude {big:.3g}, beyond float32 range")
    return a


def _check_finite(a: np.ndarray, what: str) -> None:
    if a.dtype.kind == "f":
        bad = ~np.isfinite(a)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            kind = "NaN" if np.isnan(a[r, c]) else "inf"
            raise ValueError(f"{what} {r} contains {kind} (feature {c}); features must be finite")


def _scale_exponent(x: np.ndarray) -> int:
    """e with max|x| * 2^-e in [0.5, 1) (0 for an all-zero array)."""
    m = float(np.abs(x).max()) if x.size else 0.0
    return int(np.frexp(m)[1]) if m > 0 else 0


def _pack(x: np.ndarray, exp: int, rows: int, cols: int, dtype) -> np.ndarray:
    """x * 2^-exp, zero-padded to (rows, cols), as a C-contiguous array of dtype."""
    out = np.zeros((rows, cols), dtype)
    x = np.asarray(x)
    x = x if x.dtype.kind == "f" else x.astype(np.float64)
    out[:x.shape[0], :x.shape[1]] = np.ldexp(x, np.int32(-exp))  # exact: power of two
    return out


def _check_query_range(qbuf: np.ndarray, dim_pad: int) -> None:
    """Scaled queries must keep every distance below 2^126: (|q| + 1)^2 * D < 2^126."""
    m = float(np.abs(qbuf).max(initial=0.0))
    if (m + 1.0) ** 2 * dim_pad >= 2.0 ** 126:
        raise ValueError(f"query magnitude is {m:.3g} times the database's largest value: "
                         "float32 distances would overflow")


def _unscale_dists(d: np.ndarray, exp: int) -> np.ndarray:
    out = np.ldexp(d.astype(np.float64), 2 * exp)
    return np.minimum(out, np.finfo(np.float32).max).astype(np.float32)


# ----------------------------------------------------------------------------- catalogue search

def rank_features(query: np.ndarray, db: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All rows of ``db`` (N, D) ordered by squared L2 distance to ``query`` (D,).

    Both sides are L2-normalised first (float64, after dividing by the largest magnitude, so huge
    values rank like small ones); the distance is ``[q != 0] + [d != 0] - 2 q.d`` with the
    normalised rows, so an all-zero row is at distance 1 from any unit row and identical rows get
    identical distances (same row-wise sum). Returns (order (N,) int64, sq_dists (N,) float64 in
    that order). Ties go to the lower row index.
    """
    q = np.asarray(query)
    db = np.asarray(db)
    if db.ndim != 2 or q.shape != (db.shape[1],):
        raise ValueError(f"query must be (D,) and db (N, D); got {q.shape} and {db.shape}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(db))):
        raise ValueError("features contain NaN or infinity")
    qn, q_nz = unit_rows(q[None])
    d = np.empty(len(db))
    for r0 in range(0, len(db), RANK_ROWS):         # row-wise arithmetic: blocks change no bit
        dn, d_nz = unit_rows(db[r0:r0 + RANK_ROWS])
        d[r0:r0 + RANK_ROWS] = q_nz[0] + d_nz - 2.0 * (dn * qn).sum(axis=1)
    order = np.lexsort((np.arange(d.size), d))
    return order, d[order]


@dataclass
class CatalogMatch:
    """One catalogue row matched by ``search_catalog``."""

    row: int
    mesh: int
    view: int
    azimuth: float
    elevation: float
    score: float


def search_catalog(query: np.ndarray, feats: np.ndarray, mesh_ids: np.ndarray,
                   views: np.ndarray, azimuth: np.ndarray, elevation: np.ndarray,
                   top: int = 5, *, index=None) -> list[CatalogMatch]:
    """Best ``top`` (mesh, view) rows of a feature database for one query feature (D,).

    ``feats`` (N, D) L2-normalised rows with per-row ``mesh_ids``, ``views``, ``azimuth``,
    ``elevation`` (N,). Up to ``EXACT_ROWS`` rows (and no ``index``) the ranking is exact in
    float64 (``rank_features``). Larger databases, or a given ``index`` (a
    ``ucad_cl.search.FeatureIndex`` over ``feats`` without ids, built once for many queries),
    take the ``PRESELECT`` nearest rows from the OpenCL float32 search and re-rank those exactly;
    ties go to the lower row either way. Azimuths are canonical (azimuth 0 = the front of every
    mesh), so matches of different meshes are comparable.
    """
    q = np.asarray(query)
    if q.ndim != 1:
        raise ValueError(f"query must be (D,), got {q.shape} (search_catalog_batch takes (Q, D))")
    return search_catalog_batch(q[None], feats, mesh_ids, views, azimuth, elevation, top,
                                index=index)[0]


def search_catalog_batch(queries: np.ndarray, feats: np.ndarray, mesh_ids: np.ndarray,
                         views: np.ndarray, azimuth: np.ndarray, elevation: np.ndarray,
                         top: int = 5, *, index=None, exact: bool = True,
                         runtime: Runtime | None = None) -> list[list[CatalogMatch]]:
    """``search_catalog`` for (Q, D) queries: one OpenCL preselection for the whole batch (the
    way to many queries per second), then the exact float64 re-rank of each query's PRESELECT
    rows; ``exact=False`` keeps the index's own float32 order and squared distances (with an
    ``index``; an f32 index, or a pca index with rerank, gives exact float32 distances). Without
    an ``index`` the preselection runs on ``runtime`` (default ``get_runtime()``)."""
    feats = np.asarray(feats)
    n = feats.shape[0] if feats.ndim == 2 else -1
    cols = [np.asarray(a) for a in (mesh_ids, views, azimuth, elevation)]
    if any(c.shape != (n,) for c in cols):
        raise ValueError(f"mesh_ids, views, azimuth, elevation must all be ({n},)")
    if not 1 <= top <= n:
        raise ValueError(f"top={top} must be in 1..{n} (database rows)")
    qs = np.asarray(queries)
    if qs.ndim != 2 or qs.shape[1] != feats.shape[1]:
        raise ValueError(f"queries must be (Q, {feats.shape[1]}), got {qs.shape}")
    if index is None and n <= EXACT_ROWS:
        ranked = [rank_features(q, feats) for q in qs]
    else:
        k = min(n, max(PRESELECT, top)) if exact else top
        qn32 = unit_rows(qs)[0].astype(np.float32)
        if index is not None:
            cands, d32 = index.search(qn32, k)
        else:
            cands, d32 = search(qn32, feats, k, runtime=runtime)
        ranked = [] if exact else list(zip(cands, d32.astype(np.float64)))
        for c0 in range(0, len(qs) if exact else 0, RERANK_BATCH):   # rank_features', batched
            cand = cands[c0:c0 + RERANK_BATCH]
            qn, q_nz = unit_rows(qs[c0:c0 + RERANK_BATCH])
            dn, d_nz = unit_rows(feats[cand.ravel()])
            dn = dn.reshape(cand.shape + (-1,))
            d = q_nz[:, None] + d_nz.reshape(cand.shape) - 2.0 * (dn * qn[:, None, :]).sum(axis=2)
            for c, dd in zip(cand, d):
                o = np.lexsort((c, dd))
                ranked.append((c[o], dd[o]))
    return [[CatalogMatch(row=int(r), mesh=int(cols[0][r]), view=int(cols[1][r]),
                          azimuth=float(cols[2][r]), elevation=float(cols[3][r]),
                          score=float(s)) for r, s in zip(rows[:top], d[:top])]
            for rows, d in ranked]
