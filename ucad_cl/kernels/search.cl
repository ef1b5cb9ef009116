/* search.cl: exact k-nearest-neighbour search by squared L2 distance, brute force.
 *
 * Distance. d(q, x) = sum_j (q_j - x_j)^2, computed by DIRECT DIFFERENCE, never by the expansion
 * |q|^2 - 2 q.x + |x|^2: the expansion cancels catastrophically for near-identical vectors (it
 * returns ~1e-7 |q|^2 noise, even negative values, where the true distance is 0 or tiny), which
 * reorders near-duplicates and breaks the tie rule. The difference form gives exactly 0 for
 * identical rows and a relative error below (D/16 + 4) * 2^-24 on every distance. Each term is
 * one explicit fma(t, t, acc) (single rounding); FP_CONTRACT is OFF elsewhere.
 *
 * Fixed summation order (so every kernel here returns bit-identical distances for the same pair):
 * the feature axis is padded with zeros to a multiple of 16 (exact: (0 - 0)^2 = 0); lane l of a
 * float16 accumulator sums the terms j = l, l + 16, l + 32, ... in increasing j; the 16 lanes are
 * then folded pairwise (hsum16: lo + hi down to one float).
 *
 * Tie rule. Candidates are ordered by (distance, row) lexicographically: equal distances -> lower
 * database row first. Every top-k routine below inserts with that comparison, so the result does
 * not depend on work-item order.
 *
 * Kernels
 *   sq_l2_tile       (Q, N) distances, database float32 (DB_HALF undefined) or half (DB_HALF).
 *                    One work-item computes a QB x RB register block (QB queries x RB rows)
 *                    straight from global memory; a work-group holds LQ query blocks of one row
 *                    block, so the RB rows stay in L1 while every query block reads them (each
 *                    row leaves DRAM once per batch). QB, RB are build options.
 *   topk_rows        per (query, row chunk) the k smallest (distance, row) of the chunk, sorted.
 *   topk_merge       per query the k smallest of M candidates (distance, row); row < 0 = none.
 *   sq_l2_gather     distances of Q queries to R listed rows each (exact re-rank for PCA mode).
 *   sq_l2_dot_tile   (Q, N) distances by the expansion, for preselecting re-rank candidates only.
 *
 * Measured on PoCL (2 Zen cores, AVX-512; 100 queries x 72,000 rows x 512):
 *   - loops over QB/RB must be unrolled explicitly (_Pragma("unroll")): without it PoCL keeps the
 *     accumulators in stack memory (70 ms -> 22 ms);
 *   - copying the row tile into local memory behind a barrier (the GPU recipe) was 3-6x SLOWER
 *     (PoCL splits the work-item loop at the barrier); reading cached global memory wins;
 *   - fusing the top-k into the distance kernel (private top-k lists per work-item) was 2x slower
 *     than writing the distance matrix and selecting in topk_rows (~5 ms).
 */
#include "common.h"

#ifndef QB
#define QB 4
#endif
#ifndef RB
#define RB 4
#endif
/* KMAX: from ucad_cl/abi.py (-D) */

typedef struct {
    int n_queries;      /* Q (real, unpadded) */
    int n_rows;         /* N (real, unpadded) */
    int dim16;          /* padded feature length / 16 */
    int q_stride;       /* padded Q: rows of the query matrix (multiple of QB) */
    int dist_stride;    /* row length of the distance matrix (padded N, multiple of 16) */
} dist_params;

typedef struct {
    int n_queries;
    int n_rows;         /* valid columns of the distance matrix */
    int dist_stride;
    int chunk;          /* rows per chunk (topk_rows) */
    int n_chunks;
    int k;
} topk_params;

typedef struct {
    int n_queries;
    int n_cand;         /* M candidates per query */
    int k;
} merge_params;

typedef struct {
    int n_queries;
    int dim16;
    int n_cand;         /* R rows per query */
} gather_params;

static inline float hsum16(float16 a) {
    float8 b = a.lo + a.hi;
    float4 c = b.lo + b.hi;
    float2 d = c.lo + c.hi;
    return d.lo + d.hi;
}

#ifdef DB_HALF
#define LOAD_ROW(db, r, j, dim16) vload_half16((size_t)(r) * (dim16) + (j), (db))
#define DB_T half
#else
#define LOAD_ROW(db, r, j, dim16) vload16((size_t)(r) * (dim16) + (j), (db))
#define DB_T float
#endif

/* global (q_stride / QB, dist_stride / RB); local (a divisor of q_stride / QB, 1). */
kernel void sq_l2_tile(dist_params p, global const float *queries, global const DB_T *db,
                       global float *dist) {
    const int qb = get_global_id(0) * QB;
    const int rb = get_global_id(1) * RB;
    float16 acc[QB][RB];
    _Pragma("unroll")
    for (int a = 0; a < QB; ++a)
        _Pragma("unroll")
        for (int b = 0; b < RB; ++b) acc[a][b] = (float16)(0.0f);
    for (int j = 0; j < p.dim16; ++j) {
        float16 x[RB];
        _Pragma("unroll")
        for (int b = 0; b < RB; ++b) x[b] = LOAD_ROW(db, rb + b, j, p.dim16);
        _Pragma("unroll")
        for (int a = 0; a < QB; ++a) {
            const float16 q = vload16((size_t)(qb + a) * p.dim16 + j, queries);
            _Pragma("unroll")
            for (int b = 0; b < RB; ++b) {
                const float16 t = q - x[b];
                acc[a][b] = fma(t, t, acc[a][b]);
            }
        }
    }
    _Pragma("unroll")
    for (int a = 0; a < QB; ++a)
        _Pragma("unroll")
        for (int b = 0; b < RB; ++b)
            dist[(size_t)(qb + a) * p.dist_stride + rb + b] = hsum16(acc[a][b]);
}

static inline float hsum8(float8 a) {
    float4 c = a.lo + a.hi;
    float2 d = c.lo + c.hi;
    return d.lo + d.hi;
}

#ifndef DQB
#define DQB 4
#endif
#ifndef DRB
#define DRB 2
#endif

/* Candidate preselection only (PCA mode with re-rank): d = |q|^2 + |x|^2 - 2 q.x, the EXPANSION,
 * one fma per term instead of a difference and an fma, with float8 accumulators so that a
 * DQB x DRB block fits the 16 AVX2 registers. It cancels for near-identical vectors (error
 * ~1e-7 |q|^2, see the top of this file), which only reorders near-ties among the candidates:
 * every candidate is then re-ranked by sq_l2_gather's exact direct differences.
 * global (q_stride / DQB, dist_stride / DRB); local (a divisor of q_stride / DQB, 1);
 * q_norm2 (q_stride), x_norm2 (dist_stride): squared norms of the same float32 rows. */
kernel void sq_l2_dot_tile(dist_params p, global const float *queries, global const float *db,
                           global const float *q_norm2, global const float *x_norm2,
                           global float *dist) {
    const int qb = get_global_id(0) * DQB;
    const int rb = get_global_id(1) * DRB;
    const int dim8 = 2 * p.dim16;
    float8 acc[DQB][DRB];
    _Pragma("unroll")
    for (int a = 0; a < DQB; ++a)
        _Pragma("unroll")
        for (int b = 0; b < DRB; ++b) acc[a][b] = (float8)(0.0f);
    for (int j = 0; j < dim8; ++j) {
        float8 x[DRB];
        _Pragma("unroll")
        for (int b = 0; b < DRB; ++b) x[b] = vload8((size_t)(rb + b) * dim8 + j, db);
        _Pragma("unroll")
        for (int a = 0; a < DQB; ++a) {
            const float8 q = vload8((size_t)(qb + a) * dim8 + j, queries);
            _Pragma("unroll")
            for (int b = 0; b < DRB; ++b) acc[a][b] = fma(q, x[b], acc[a][b]);
        }
    }
    _Pragma("unroll")
    for (int a = 0; a < DQB; ++a)
        _Pragma("unroll")
        for (int b = 0; b < DRB; ++b)
            dist[(size_t)(qb + a) * p.dist_stride + rb + b] =
                (q_norm2[qb + a] + x_norm2[rb + b]) - 2.0f * hsum8(acc[a][b]);
}

/* Insert (d, r) into the sorted list (kd, kr) of length n <= k, keeping the k smallest by
 * (distance, row). Returns the new length. */
static inline int topk_insert(float *kd, int *kr, int n, int k, float d, int r) {
    if (n == k) {
        if (d > kd[k - 1] || (d == kd[k - 1] && r > kr[k - 1])) return n;
        --n;                               /* drop the current last */
    }
    int i = n;
    while (i > 0 && (d < kd[i - 1] || (d == kd[i - 1] && r < kr[i - 1]))) {
        kd[i] = kd[i - 1];
        kr[i] = kr[i - 1];
        --i;
    }
    kd[i] = d;
    kr[i] = r;
    return n + 1;
}

/* topk_insert for a row larger than every row already listed (rows scanned in increasing order):
 * then (distance, row) order reduces to distance order, equal distances staying in front.
 * The caller ensures n < k or d < kd[k - 1]. */
static inline int topk_insert_ascending(float *kd, int *kr, int n, int k, float d, int r) {
    int i = n == k ? k - 1 : n;
    while (i > 0 && d < kd[i - 1]) {
        kd[i] = kd[i - 1];
        kr[i] = kr[i - 1];
        --i;
    }
    kd[i] = d;
    kr[i] = r;
    return n == k ? k : n + 1;
}

/* global (n_chunks, Q). chunk and dist_stride are multiples of 16 (aligned float16 loads).
 * Output cand_d/cand_r (Q, n_chunks, k); unused slots row -1, +inf. */
kernel void topk_rows(topk_params p, global const float *dist, global float *cand_d,
                      global int *cand_r) {
    const int s = get_global_id(0);
    const int q = get_global_id(1);
    if (s >= p.n_chunks || q >= p.n_queries) return;
    float kd[KMAX];
    int kr[KMAX];
    int n = 0;
    const int r0 = s * p.chunk;
    const int r1 = min(p.n_rows, r0 + p.chunk);
    global const float *row = dist + (size_t)q * p.dist_stride;
    /* Rows arrive in increasing order, so a distance equal to the current k-th never enters.
     * Sixteen distances are tested at once against the k-th; most blocks are skipped whole. */
    float worst = INFINITY;
    for (int r = r0; r < r1; r += 16) {
        const float16 v = vload16(0, row + r);
        if (n == p.k && !any(v < (float16)(worst))) continue;
        float vs[16];
        vstore16(v, 0, vs);
        const int nb = min(16, r1 - r);
        for (int b = 0; b < nb; ++b) {
            if (n < p.k || vs[b] < worst) {
                n = topk_insert_ascending(kd, kr, n, p.k, vs[b], r + b);
                worst = kd[n - 1];
            }
        }
    }
    const size_t o = ((size_t)q * p.n_chunks + s) * p.k;
    for (int i = 0; i < p.k; ++i) {
        cand_d[o + i] = i < n ? kd[i] : INFINITY;
        cand_r[o + i] = i < n ? kr[i] : -1;
    }
}

/* global (Q). cand (Q, n_cand) -> out (Q, k); rows < 0 are skipped. */
kernel void topk_merge(merge_params p, global const float *cand_d, global const int *cand_r,
                       global float *out_d, global int *out_r) {
    const int q = get_global_id(0);
    if (q >= p.n_queries) return;
    float kd[KMAX];
    int kr[KMAX];
    int n = 0;
    const size_t o = (size_t)q * p.n_cand;
    for (int i = 0; i < p.n_cand; ++i) {
        const int r = cand_r[o + i];
        if (r >= 0) n = topk_insert(kd, kr, n, p.k, cand_d[o + i], r);
    }
    for (int i = 0; i < p.k; ++i) {
        out_d[(size_t)q * p.k + i] = i < n ? kd[i] : INFINITY;
        out_r[(size_t)q * p.k + i] = i < n ? kr[i] : -1;
    }
}

/* global (R, Q). dist[q, i] = d(query q, row rows[q, i]) with the summation order above. */
kernel void sq_l2_gather(gather_params p, global const float *queries, global const float *db,
                         global const int *rows, global float *dist) {
    const int i = get_global_id(0);
    const int q = get_global_id(1);
    if (i >= p.n_cand || q >= p.n_queries) return;
    const int r = rows[(size_t)q * p.n_cand + i];
    float16 acc = (float16)(0.0f);
    if (r >= 0) {
        for (int j = 0; j < p.dim16; ++j) {
            const float16 t = vload16((size_t)q * p.dim16 + j, queries)
                              - vload16((size_t)r * p.dim16 + j, db);
            acc = fma(t, t, acc);
        }
    }
    dist[(size_t)q * p.n_cand + i] = r >= 0 ? hsum16(acc) : INFINITY;
}
