/* raster.cl: exact, deterministic rasterization of triangle-id / material-id / depth maps for
 * many views of one mesh in one launch.
 *
 * Coordinates. Vertices are in the canonical frame (float32). Each view v has a 3x4 matrix
 * P_v = K [R|t] (float32, computed in float64 on the host), giving homogeneous image coordinates
 * (u, v, w) = P_v (x, y, z, 1), where w is the linear camera-space depth z. The pixel position is
 * (u/w, v/w) in OpenCV image coordinates: pixel (i, j) has its sample point at its centre
 * (j + 0.5, i + 0.5).
 *
 * Exactness. Clipped vertices are snapped to a fixed-point grid of 1/256 pixel (SUB_BITS = 8);
 * coverage uses exact 64-bit integer edge functions with a top-left fill rule (D3D's: with y
 * down, an edge is owned when it goes up, or is horizontal and goes right), so a pixel centre on an
 * edge shared by two triangles is covered by exactly one of them. Both windings are drawn (CAD
 * meshes are two-sided); a triangle of zero snapped area covers nothing.
 *
 * Clipping. Triangles are clipped in homogeneous space against the near plane (w >= near) and a
 * guard band (|pixel| within GUARD pixels of the image), which bounds snapped coordinates below
 * 2^22 and edge-function products below 2^46. An edge's intersection with a plane is computed
 * from its two endpoints in a canonical order (lexicographic on (u, v, w)), so two triangles that
 * share the edge get bit-identical clipped vertices and stay watertight after clipping.
 *
 * Visibility. Every covered pixel proposes the 64-bit key (float bits of depth z > 0) << 32 |
 * face index, and the pixel keeps the minimum via atomic_min: nearest depth wins, equal depths go
 * to the lower face index, whatever the thread order. Depth is interpolated perspective-correctly
 * (1/z is affine in screen space) from the exact integer barycentrics, with the triangle's
 * vertices in a canonical rotation (first the vertex with the smallest (y, x)) so that duplicate
 * faces listed in another vertex order get identical depths.
 *
 * Work split. project_vertices: clip code and snapped position (and, for the serial path, depth)
 * of every (vertex, view), once. Then one of two paths, which give identical bytes (the same
 * keys, computed by the same expressions; tests/test_render.py checks it):
 *  - parallel (GPUs): raster_small, one work-item per (face, view). A triangle whose clipped
 *    bounding box exceeds BIG_PIXELS pixels is appended to a list instead, and raster_big spreads
 *    each listed triangle over LANES work-items (rows interleaved). If the list overflows, the host
 *    enlarges it and reruns raster_small: atomic_min is idempotent, so a rerun only repeats work.
 *  - serial (CPUs): raster_views_serial, one work-item per view; see its comment.
 */
#include "common.h"

#define SUB_BITS 8
#define SUB_ONE 256L
#define SUB_HALF 128L
#define GUARD 8192.0f
#define MAX_POLY 9

#ifndef BIG_PIXELS
#define BIG_PIXELS 1024
#endif

typedef struct { float u, v, w; } hvert;

typedef struct {
    int width, height;
    int n_faces, n_views;
    float near;
    uint big_capacity;
} raster_params;

static inline hvert project(global const float *P, float x, float y, float z) {
    hvert h;
    h.u = P[0] * x + P[1] * y + P[2] * z + P[3];
    h.v = P[4] * x + P[5] * y + P[6] * z + P[7];
    h.w = P[8] * x + P[9] * y + P[10] * z + P[11];
    return h;
}

/* Signed distance of a homogeneous vertex to clip plane k (inside when >= 0). */
static inline float plane_dist(hvert p, int k, float near, float W, float H) {
    switch (k) {
        case 0: return p.w - near;
        case 1: return p.u + GUARD * p.w;
        case 2: return (W + GUARD) * p.w - p.u;
        case 3: return p.v + GUARD * p.w;
        default: return (H + GUARD) * p.w - p.v;
    }
}

static inline int vert_less(hvert a, hvert b) {
    if (a.u != b.u) return a.u < b.u;
    if (a.v != b.v) return a.v < b.v;
    return a.w < b.w;
}

/* Intersection of segment (p, q) with plane k, computed in canonical endpoint order. */
static inline hvert intersect(hvert p, hvert q, int k, float near, float W, float H) {
    hvert a = p, b = q;
    if (vert_less(q, p)) { a = q; b = p; }
    float da = plane_dist(a, k, near, W, H), db = plane_dist(b, k, near, W, H);
    float t = da / (da - db);
    hvert r;
    r.u = a.u + t * (b.u - a.u);
    r.v = a.v + t * (b.v - a.v);
    r.w = a.w + t * (b.w - a.w);
    if (k == 0) r.w = near;   /* exactly on the near plane */
    return r;
}

/* Round half to even for |x| <= 2^22, as rint() does, but as two additions PoCL vectorizes
 * (rint() was a scalar library call costing more than the rest of project_vertices): adding
 * 1.5 * 2^23 moves x where the float spacing is 1, so the sum is rounded to an integer (ties to
 * even), and the subtraction is exact. Needs FP_CONTRACT OFF and no fast-math (common.h). */
static inline float round_even(float x) {
    const float magic = 12582912.0f;
    return (x + magic) - magic;
}

/* Snapped fixed-point position (1/256 px) of a vertex inside the guard band (|coordinate| <=
 * (8192 + GUARD) px = 2^22 / 256): one correctly rounded division, exact products, round half
 * to even: the same bits on every device. */
static inline long2 snap(hvert p) {
    float s = 256.0f / p.w;
    return (long2)((long)round_even(p.u * s), (long)round_even(p.v * s));
}

/* Pixel range [lo, hi] whose centres lie in [a, b] (fixed point), clamped to [0, n-1]. */
static inline int2 pixel_span(long a, long b, int n) {
    long lo = a - SUB_HALF, hi = b - SUB_HALF;
    int2 r;
    r.x = lo <= 0 ? 0 : (int)((lo + SUB_ONE - 1) / SUB_ONE);
    r.y = hi < 0 ? -1 : (int)min(hi / SUB_ONE, (long)(n - 1));
    return r;
}

/* Rasterize one snapped triangle into one view's key map, rows row0, row0+step, ...
 * Instantiated for 64-bit edge functions (any triangle inside the guard band) and for 32-bit
 * ones, used only when the fixed-point bounding box (xmax - xmin) * (ymax - ymin) is at most
 * BIG_PIXELS * 256^2 = 2^26: coordinates are taken relative to the first covered pixel centre o,
 * which lies inside the box, so every x difference is at most xmax - xmin and every y difference
 * at most ymax - ymin; each edge-function product (an x difference times a y difference) is then
 * at most 2^26 and every edge function, area and step at most 2^27: exact in 32 bits.
 */
#define DEFINE_RASTER_TRIANGLE(NAME, T, VEC)                                                      \
static void NAME(long2 p0, long2 p1, long2 p2, float z0, float z1, float z2,                  \
                 uint face, int width, int height, int row0, int row_step,                     \
                 int exclusive, global ulong *keys) {                                          \
    /* canonical rotation: smallest (y, x) first; keeps the winding */                        \
    int r = 0;                                                                                 \
    if (p1.y < p0.y || (p1.y == p0.y && p1.x < p0.x)) r = 1;                                   \
    long2 pr = r ? p1 : p0;                                                                    \
    if (p2.y < pr.y || (p2.y == pr.y && p2.x < pr.x)) r = 2;                                   \
    long2 la, lb, lc; float za, zb, zc;                                                        \
    if (r == 0)      { la = p0; lb = p1; lc = p2; za = z0; zb = z1; zc = z2; }                 \
    else if (r == 1) { la = p1; lb = p2; lc = p0; za = z1; zb = z2; zc = z0; }                 \
    else             { la = p2; lb = p0; lc = p1; za = z2; zb = z0; zc = z1; }                 \
    int2 xs = pixel_span(min(la.x, min(lb.x, lc.x)), max(la.x, max(lb.x, lc.x)), width);       \
    int2 ys = pixel_span(min(la.y, min(lb.y, lc.y)), max(la.y, max(lb.y, lc.y)), height);      \
    if (xs.x > xs.y || ys.x > ys.y) return;                                                    \
    /* origin: the first pixel centre of the box */                                            \
    long2 o = (long2)((long)xs.x * SUB_ONE + SUB_HALF, (long)ys.x * SUB_ONE + SUB_HALF);        \
    VEC a = CONVERT_##T(la - o), b = CONVERT_##T(lb - o), c = CONVERT_##T(lc - o);             \
    T area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);                           \
    if (area == 0) return;                                                                     \
    if (area < 0) {   /* make the winding positive (clockwise on screen, y down) */            \
        VEC t = b; b = c; c = t;                                                               \
        float tz = zb; zb = zc; zc = tz;                                                       \
        area = -area;                                                                          \
    }                                                                                          \
    /* edge functions E_ab(P) = (b - a) x (P - a); bias -1 on edges that are not owned */     \
    T bias_ab = owned_##T(a, b) ? 0 : -1;                                                      \
    T bias_bc = owned_##T(b, c) ? 0 : -1;                                                      \
    T bias_ca = owned_##T(c, a) ? 0 : -1;                                                      \
    /* z = area / (E_bc / za + E_ca / zb + E_ab / zc), without per-vertex reciprocals */       \
    float wa = zb * zc, wb = za * zc, wc = za * zb, num = (float)area * za * wa;               \
    T s_ab = -(b.y - a.y) * (T)SUB_ONE, s_bc = -(c.y - b.y) * (T)SUB_ONE,                      \
      s_ca = -(a.y - c.y) * (T)SUB_ONE;                                                        \
    for (int i = ys.x + row0; i <= ys.y; i += row_step) {                                      \
        T py = (T)(i - ys.x) * (T)SUB_ONE;                                                     \
        T e_ab = (b.x - a.x) * (py - a.y) - (b.y - a.y) * (-a.x);                              \
        T e_bc = (c.x - b.x) * (py - b.y) - (c.y - b.y) * (-b.x);                              \
        T e_ca = (a.x - c.x) * (py - c.y) - (a.y - c.y) * (-c.x);                              \
        global ulong *row = keys + (long)i * width;                                            \
        for (int j = xs.x; j <= xs.y; ++j) {                                                   \
            if (e_ab + bias_ab >= 0 && e_bc + bias_bc >= 0 && e_ca + bias_ca >= 0) {           \
                /* weight of a is E_bc / area, of b is E_ca / area, of c is E_ab / area */     \
                float den = (float)e_bc * wa + (float)e_ca * wb + (float)e_ab * wc;            \
                float z = num / den;                                                           \
                PLOT(row + j, z, face, exclusive);                                             \
            }                                                                                  \
            e_ab += s_ab; e_bc += s_bc; e_ca += s_ca;                                          \
        }                                                                                      \
    }                                                                                          \
}

/* exclusive: the calling work-item owns the whole view (serial path), so a plain min will do */
#ifdef UCAD_COUNT_COVERAGE    /* test build: count how often each pixel centre is covered */
#define PLOT(ptr, z, face, exclusive) atom_add((ptr), 1UL)
#else
#define PLOT(ptr, z, face, exclusive) \
    keep_min((ptr), ((ulong)as_uint(z) << 32) | (ulong)(face), (exclusive))
#endif
static inline void keep_min(global ulong *p, ulong key, int exclusive) {
    if (exclusive) *p = min(*p, key);
    else atom_min(p, key);
}
#define CONVERT_long(x) (x)
#define CONVERT_int(x) convert_int2(x)
/* pixel_span in 32 bits for snapped coordinates (|a|, |b| <= 2^22): same result */
static inline int2 pixel_span32(int a, int b, int n) {
    int lo = a - (int)SUB_HALF, hi = b - (int)SUB_HALF;
    int2 r;
    r.x = lo <= 0 ? 0 : (lo + (int)SUB_ONE - 1) >> SUB_BITS;
    r.y = hi < 0 ? -1 : min(hi >> SUB_BITS, n - 1);
    return r;
}

static inline int owned_long(long2 a, long2 b) {
    long dx = b.x - a.x, dy = b.y - a.y;
    return dy < 0 || (dy == 0 && dx > 0);
}
static inline int owned_int(int2 a, int2 b) {
    int dx = b.x - a.x, dy = b.y - a.y;
    return dy < 0 || (dy == 0 && dx > 0);
}
DEFINE_RASTER_TRIANGLE(raster_triangle64, long, long2)
DEFINE_RASTER_TRIANGLE(raster_triangle32, int, int2)

/* Per (vertex, view): for a vertex inside every clip plane, its snapped position (x, y); for
 * one outside some plane, (CLIPPED, clip code): bit k set when outside plane k, NaN counts as
 * outside. 8 bytes per vertex and view. Depth w goes to a separate buffer when store_depth is
 * set (serial path, which reads it per vertex); the parallel path recomputes it instead (same
 * expression, same bits), which measured cheaper there than the extra bandwidth. */
#define CLIPPED INT_MIN
kernel void project_vertices(global const float *verts, global const float *P, raster_params prm,
                             uint n_verts, global int2 *out, global float *depth_out,
                             uint store_depth) {
    uint v = get_global_id(0), view = get_global_id(1);
    if (v >= n_verts || view >= (uint)prm.n_views) return;
    float W = (float)prm.width, H = (float)prm.height;
    hvert h = project(P + 12 * view, verts[3 * v], verts[3 * v + 1], verts[3 * v + 2]);
    /* straight-line plane tests (same expressions as plane_dist), so PoCL can vectorize */
    int code = (!(h.w - prm.near >= 0.0f))
             | (!(h.u + GUARD * h.w >= 0.0f)) << 1
             | (!((W + GUARD) * h.w - h.u >= 0.0f)) << 2
             | (!(h.v + GUARD * h.w >= 0.0f)) << 3
             | (!((H + GUARD) * h.w - h.v >= 0.0f)) << 4;
    long2 sn = snap(h);
    if (store_depth) depth_out[(long)view * n_verts + v] = h.w;
    out[(long)view * n_verts + v] = code ? (int2)(CLIPPED, code) : (int2)((int)sn.x, (int)sn.y);
}

static inline float depth_of(global const float *Pv, global const float *verts, uint i) {
    return project(Pv, verts[3 * i], verts[3 * i + 1], verts[3 * i + 2]).w;
}

/* Clip (rarely needed) and rasterize one face in one view. mode:
 *  MODE_SMALL  parallel first pass: if the bounding box is bigger than BIG_PIXELS, push
 *              (face, view) to the list instead;
 *  MODE_LANES  parallel second pass: rows row0, row0 + row_step, ... of a listed face;
 *  MODE_OWNER  serial path: the work-item owns the view; draw the face whatever its size. */
#define MODE_SMALL 0
#define MODE_LANES 1
#define MODE_OWNER 2
static void raster_face(global const float *verts, global const uint *faces,
                        global const float *P, global const int2 *pverts, uint n_verts,
                        raster_params prm, uint face, uint view,
                        int row0, int row_step, int mode,
                        global ulong *keys, global uint *big_list, volatile global uint *big_count) {
    uint i0 = faces[3 * face], i1 = faces[3 * face + 1], i2 = faces[3 * face + 2];
    global const int2 *pv = pverts + (long)view * n_verts;
    global const float *Pv = P + 12 * view;
    int2 q0 = pv[i0], q1 = pv[i1], q2 = pv[i2];
    int clipped = (q0.x == CLIPPED) | (q1.x == CLIPPED) | (q2.x == CLIPPED);
    if (q0.x == CLIPPED && q1.x == CLIPPED && q2.x == CLIPPED && (q0.y & q1.y & q2.y))
        return;                                           /* wholly outside one plane */
    global ulong *kv = keys + (long)view * prm.width * prm.height;
    long2 s[MAX_POLY];
    float zs[MAX_POLY];
    int n;
    if (!clipped) {                                       /* common case: no clipping */
        /* most small faces cover no pixel centre: leave in 32-bit math, before anything else */
        int2 xs = pixel_span32(min(q0.x, min(q1.x, q2.x)), max(q0.x, max(q1.x, q2.x)), prm.width);
        int2 ys = pixel_span32(min(q0.y, min(q1.y, q2.y)), max(q0.y, max(q1.y, q2.y)), prm.height);
        if (xs.x > xs.y || ys.x > ys.y) return;
        s[0] = (long2)(q0.x, q0.y); s[1] = (long2)(q1.x, q1.y); s[2] = (long2)(q2.x, q2.y);
        n = 3;
    } else {                                              /* Sutherland-Hodgman, 5 planes */
        float W = (float)prm.width, H = (float)prm.height;
        hvert poly[MAX_POLY], tmp[MAX_POLY];
        poly[0] = project(Pv, verts[3 * i0], verts[3 * i0 + 1], verts[3 * i0 + 2]);
        poly[1] = project(Pv, verts[3 * i1], verts[3 * i1 + 1], verts[3 * i1 + 2]);
        poly[2] = project(Pv, verts[3 * i2], verts[3 * i2 + 1], verts[3 * i2 + 2]);
        n = 3;
        for (int k = 0; k < 5 && n >= 3; ++k) {
            int m = 0;
            for (int e = 0; e < n; ++e) {
                hvert p = poly[e], q = poly[(e + 1) % n];
                float dp = plane_dist(p, k, prm.near, W, H), dq = plane_dist(q, k, prm.near, W, H);
                if (!(dp == dp) || !(dq == dq)) return;   /* NaN vertex: draw nothing */
                if (dp >= 0.0f) tmp[m++] = p;
                if ((dp >= 0.0f) != (dq >= 0.0f) && m < MAX_POLY) tmp[m++] = intersect(p, q, k, prm.near, W, H);
            }
            n = m;
            for (int e = 0; e < n; ++e) poly[e] = tmp[e];
        }
        if (n < 3) return;
        for (int e = 0; e < n; ++e) { s[e] = snap(poly[e]); zs[e] = poly[e].w; }
    }
    long xmin = s[0].x, xmax = s[0].x, ymin = s[0].y, ymax = s[0].y;
    for (int e = 1; e < n; ++e) {
        xmin = min(xmin, s[e].x); xmax = max(xmax, s[e].x);
        ymin = min(ymin, s[e].y); ymax = max(ymax, s[e].y);
    }
    {   /* nothing to do when no pixel centre lies in the box (most tiny triangles) */
        int2 xs = pixel_span(xmin, xmax, prm.width), ys = pixel_span(ymin, ymax, prm.height);
        if (xs.x > xs.y || ys.x > ys.y) return;
    }
    if (!clipped) {
        zs[0] = depth_of(Pv, verts, i0); zs[1] = depth_of(Pv, verts, i1); zs[2] = depth_of(Pv, verts, i2);
    }
    int exclusive = mode == MODE_OWNER;
    if (mode != MODE_LANES) {
        int2 xs = pixel_span(xmin, xmax, prm.width), ys = pixel_span(ymin, ymax, prm.height);
        /* small: at most BIG_PIXELS pixel centres to visit AND a fixed-point box of at most
         * BIG_PIXELS square pixels (the 32-bit edge-function bound, see raster_triangle32) */
        int small = (long)(xs.y - xs.x + 1) * (long)(ys.y - ys.x + 1) <= BIG_PIXELS &&
                    (xmax - xmin) * (ymax - ymin) <= (long)BIG_PIXELS * SUB_ONE * SUB_ONE;
        if (small) {
            for (int e = 1; e + 1 < n; ++e)   /* fan: (0, e, e+1) */
                raster_triangle32(s[0], s[e], s[e + 1], zs[0], zs[e], zs[e + 1],
                                  face, prm.width, prm.height, 0, 1, exclusive, kv);
            return;
        }
        if (mode == MODE_SMALL) {
            uint slot = atomic_inc(big_count);
            if (slot < prm.big_capacity) { big_list[2 * slot] = face; big_list[2 * slot + 1] = view; }
            return;
        }
    }
    for (int e = 1; e + 1 < n; ++e)
        raster_triangle64(s[0], s[e], s[e + 1], zs[0], zs[e], zs[e + 1],
                          face, prm.width, prm.height, row0, row_step, exclusive, kv);
}

/* One work-item per (face = global id 0, view = global id 1). */
kernel void raster_small(global const float *verts, global const uint *faces, global const float *P,
                         global const int2 *pverts, uint n_verts, raster_params prm,
                         global ulong *keys, global uint *big_list, volatile global uint *big_count) {
    uint face = get_global_id(0), view = get_global_id(1);
    if (face >= (uint)prm.n_faces || view >= (uint)prm.n_views) return;
    raster_face(verts, faces, P, pverts, n_verts, prm, face, view, 0, 1, MODE_SMALL, keys, big_list,
                big_count);
}

/* One work-item per (listed triangle = global id 0, lane = global id 1 in [0, LANES)). */
kernel void raster_big(global const float *verts, global const uint *faces, global const float *P,
                       global const int2 *pverts, uint n_verts, raster_params prm,
                       global ulong *keys, global const uint *big_list, uint n_big) {
    uint entry = get_global_id(0), lane = get_global_id(1), lanes = get_global_size(1);
    if (entry >= n_big) return;
    raster_face(verts, faces, P, pverts, n_verts, prm, big_list[2 * entry], big_list[2 * entry + 1],
                (int)lane, (int)lanes, MODE_LANES, keys, 0, 0);
}

/* ---- Serial path (CPU devices): one work-item per view -------------------------------------
 * On a CPU the parallel path pays for atomics and, above all, for branches that mispredict: at
 * 100k triangles and 256 px, 44 % of (face, view) pairs cover no pixel centre, 48 % have a box of
 * at most 2 x 2 pixel centres, and which is which is data-dependent. Here one work-item owns one
 * view: it clears that view's key map, draws every face into it with plain loads and stores, and
 * resolves it, while the map (0.5 MB at 256 px) is still in its core's cache. Faces go 16 at a
 * time through explicit 16-lane vectors (PoCL maps them to AVX-512; the gathers index with signed
 * 32-bit offsets, which let LLVM use 16-wide dword gathers). A "tiny" face (not clipped, and its
 * pixel-centre box empty, or at most 4 centres in one row or one column, or 2 x 2: 96 % of the
 * pairs above) has its at most 4 candidate centres tested without branches, exactly as
 * raster_triangle32 would (same origin, canonical rotation, winding, biases and depth
 * expression); only covered candidates are then merged, lane by lane, by a plain min. Any other
 * face goes through raster_face (MODE_OWNER). Output is the parallel path's, bit for bit, and
 * depends on no thread count: each view is one work-item's sequential loop, and the min of keys
 * does not depend on the order faces are drawn in. (On a GPU, one work-item per view would leave
 * the device nearly idle; the parallel path is the one for it.)
 */
#define LANES16 16
/* The 16 values p[ix.s0] .. p[ix.sf] as a T vector (int offsets: see above). */
#define GATHER16(T, p, ix) (T)(                                                                 \
    (p)[(int)(ix).s0], (p)[(int)(ix).s1], (p)[(int)(ix).s2], (p)[(int)(ix).s3],                 \
    (p)[(int)(ix).s4], (p)[(int)(ix).s5], (p)[(int)(ix).s6], (p)[(int)(ix).s7],                 \
    (p)[(int)(ix).s8], (p)[(int)(ix).s9], (p)[(int)(ix).sa], (p)[(int)(ix).sb],                 \
    (p)[(int)(ix).sc], (p)[(int)(ix).sd], (p)[(int)(ix).se], (p)[(int)(ix).sf])

/* Pixel-centre span [lo, hi] of a fixed-point interval [a, b] (pixel_span32, 16 lanes). */
static inline void span16(int16 a, int16 b, int n, int16 *lo, int16 *hi) {
    int16 l = a - (int)SUB_HALF, h = b - (int)SUB_HALF;
    *lo = l <= 0 ? (int16)0 : (l + (int)SUB_ONE - 1) >> SUB_BITS;
    *hi = h < 0 ? (int16)(-1) : min(h >> SUB_BITS, (int16)(n - 1));
}

/* Edge bias of raster_triangle32 for edge a -> b: 0 when owned (top-left rule), else -1. */
static inline int16 bias16(int16 ax, int16 ay, int16 bx, int16 by) {
    int16 dx = bx - ax, dy = by - ay;
    return ~((dy < 0) | ((dy == 0) & (dx > 0)));
}

/* Bit l set where lane l of a (-1 / 0) mask is set. */
static inline uint lane_mask(int16 m) {
    uint16 b = as_uint16(m) & (uint16)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096,
                                       8192, 16384, 32768);
    uint8 b8 = b.lo | b.hi;
    uint4 b4 = b8.lo | b8.hi;
    uint2 b2 = b4.lo | b4.hi;
    return b2.x | b2.y;
}

/* Candidate c (0..3) of 16 tiny triangles: the c-th pixel centre of a row (row lanes), of a
 * column (col lanes) or of the 2 x 2 box (other lanes), from the box's first centre (xs0, ys0).
 * Stores its depth bits and its pixel index in the view, and returns the mask of the lanes that
 * cover it (ok set, centre inside the box and inside the triangle); other lanes' values are
 * meaningless. */
static inline uint tiny_candidate(int c, int16 row, int16 col, int16 xs0, int16 xs1, int16 ys0,
                                  int16 ys1, int W,
                                  int16 ax, int16 ay, int16 bx, int16 by, int16 cx, int16 cy,
                                  int16 bab, int16 bbc, int16 bca, float16 wa, float16 wb,
                                  float16 wc, float16 num, int16 ok, uint *zbits, uint *at) {
    int16 dx = row ? (int16)c : col ? (int16)0 : (int16)(c & 1);
    int16 dy = row ? (int16)0 : col ? (int16)c : (int16)(c >> 1);
    int16 px = dx * (int)SUB_ONE, py = dy * (int)SUB_ONE;
    int16 e_ab = (bx - ax) * (py - ay) - (by - ay) * (px - ax);
    int16 e_bc = (cx - bx) * (py - by) - (cy - by) * (px - bx);
    int16 e_ca = (ax - cx) * (py - cy) - (ay - cy) * (px - cx);
    int16 in = ok & (xs0 + dx <= xs1) & (ys0 + dy <= ys1) &
               (e_ab + bab >= 0) & (e_bc + bbc >= 0) & (e_ca + bca >= 0);
    float16 den = convert_float16(e_bc) * wa + convert_float16(e_ca) * wb +
                  convert_float16(e_ab) * wc;
    float16 z = num / den;   /* as raster_triangle32 */
    vstore16(as_uint16(z), 0, zbits);
    vstore16(as_uint16((ys0 + dy) * W + xs0 + dx), 0, at);
    return lane_mask(in);
}

static inline void resolve_key(ulong k, global const ushort *face_material, uint g,
                               global uint *tri_id, global ushort *mat_id, global float *depth) {
    int bg = k == 0xFFFFFFFFFFFFFFFFUL;
    uint t = (uint)(k & 0xFFFFFFFFUL);
    tri_id[g] = bg ? UCAD_BG_TRI : t;
    mat_id[g] = bg ? (ushort)UCAD_BG_MAT : (ushort)(face_material[bg ? 0 : t] + 1);
    depth[g] = bg ? INFINITY : as_float((uint)(k >> 32));
}

/* One work-item per view (global id 0). face_a/b/c: the faces' vertex indices, one array per
 * corner (the same as faces, which raster_face reads); pdepth: project_vertices' depths. */
kernel void raster_views_serial(global const float *verts, global const uint *faces,
                                global const uint *face_a, global const uint *face_b,
                                global const uint *face_c, global const float *P,
                                global const int2 *pverts, global const float *pdepth,
                                uint n_verts, raster_params prm, global ulong *keys,
                                global const ushort *face_material, global uint *tri_id,
                                global ushort *mat_id, global float *depth) {
    uint view = get_global_id(0);
    if (view >= (uint)prm.n_views) return;
    int W = prm.width, H = prm.height;
    uint F = (uint)prm.n_faces, npix = (uint)(W * H);
    global const int *pv = (global const int *)(pverts + (long)view * n_verts);
    global const float *zv = pdepth + (long)view * n_verts;
    global ulong *kv = keys + (long)view * npix;
#ifdef UCAD_COUNT_COVERAGE
    for (uint g = 0; g < npix; ++g) kv[g] = 0;
#else
    for (uint g = 0; g < npix; ++g) kv[g] = 0xFFFFFFFFFFFFFFFFUL;
#endif

    const uint16 lane = (uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    for (uint f0 = 0; f0 < F; f0 += LANES16) {
        uint16 face = (uint16)f0 + lane;
        int16 live = face < (uint16)F;
        uint16 fl = min(face, (uint16)(F - 1));
        uint16 i0, i1, i2;
        if (f0 + LANES16 <= F) {
            i0 = vload16(0, face_a + f0); i1 = vload16(0, face_b + f0);
            i2 = vload16(0, face_c + f0);
        } else {
            i0 = GATHER16(uint16, face_a, fl); i1 = GATHER16(uint16, face_b, fl);
            i2 = GATHER16(uint16, face_c, fl);
        }
        uint16 x0i = 2 * i0, x1i = 2 * i1, x2i = 2 * i2;
        uint16 y0i = x0i + 1, y1i = x1i + 1, y2i = x2i + 1;
        int16 q0x = GATHER16(int16, pv, x0i), q1x = GATHER16(int16, pv, x1i);
        int16 q2x = GATHER16(int16, pv, x2i), q0y = GATHER16(int16, pv, y0i);
        int16 q1y = GATHER16(int16, pv, y1i), q2y = GATHER16(int16, pv, y2i);
        int16 clipped = (q0x == CLIPPED) | (q1x == CLIPPED) | (q2x == CLIPPED);
        /* clipped lanes are raster_face's; zero them so no lane's arithmetic can overflow */
        q0x = clipped ? 0 : q0x; q1x = clipped ? 0 : q1x; q2x = clipped ? 0 : q2x;
        q0y = clipped ? 0 : q0y; q1y = clipped ? 0 : q1y; q2y = clipped ? 0 : q2y;
        int16 xs0, xs1, ys0, ys1;
        span16(min(q0x, min(q1x, q2x)), max(q0x, max(q1x, q2x)), W, &xs0, &xs1);
        span16(min(q0y, min(q1y, q2y)), max(q0y, max(q1y, q2y)), H, &ys0, &ys1);
        /* tiny: no pixel centre, or at most 4 in a row, 4 in a column, or a 2 x 2 box */
        int16 nx = xs1 - xs0, ny = ys1 - ys0;   /* centres per axis, minus 1 */
        int16 work = live & ~clipped & (nx >= 0) & (ny >= 0);
        int16 row = (ny == 0) & (nx <= 3), col = ~row & (nx == 0) & (ny <= 3);
        int16 tiny = (live & ~clipped & ~work) | (work & (row | col | ((nx <= 1) & (ny <= 1))));
        work &= tiny;
        uint others = lane_mask(live & ~tiny);
        if (!others && !lane_mask(work)) continue;   /* no lane covers a pixel centre */
        float16 z0 = GATHER16(float16, zv, i0), z1 = GATHER16(float16, zv, i1);
        float16 z2 = GATHER16(float16, zv, i2);
        /* canonical rotation: first the vertex with the smallest (y, x); keeps the winding */
        int16 r1 = (q1y < q0y) | ((q1y == q0y) & (q1x < q0x));
        int16 rx = r1 ? q1x : q0x, ry = r1 ? q1y : q0y;
        int16 r2 = (q2y < ry) | ((q2y == ry) & (q2x < rx));
        int16 ax = r2 ? q2x : (r1 ? q1x : q0x), ay = r2 ? q2y : (r1 ? q1y : q0y);
        int16 bx = r2 ? q0x : (r1 ? q2x : q1x), by = r2 ? q0y : (r1 ? q2y : q1y);
        int16 cx = r2 ? q1x : (r1 ? q0x : q2x), cy = r2 ? q1y : (r1 ? q0y : q2y);
        float16 za = r2 ? z2 : (r1 ? z1 : z0), zb = r2 ? z0 : (r1 ? z2 : z1);
        float16 zc = r2 ? z1 : (r1 ? z0 : z2);
        /* relative to the box's first pixel centre, as raster_triangle32 */
        int16 ox = xs0 * (int)SUB_ONE + (int)SUB_HALF, oy = ys0 * (int)SUB_ONE + (int)SUB_HALF;
        ax = work ? ax - ox : 0; ay = work ? ay - oy : 0;
        bx = work ? bx - ox : 0; by = work ? by - oy : 0;
        cx = work ? cx - ox : 0; cy = work ? cy - oy : 0;
        int16 area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax);
        int16 neg = area < 0;   /* make the winding positive: swap b and c */
        int16 tx = bx, ty = by;
        float16 tz = zb;
        bx = neg ? cx : bx; by = neg ? cy : by; zb = neg ? zc : zb;
        cx = neg ? tx : cx; cy = neg ? ty : cy; zc = neg ? tz : zc;
        area = neg ? -area : area;
        int16 bab = bias16(ax, ay, bx, by), bbc = bias16(bx, by, cx, cy);
        int16 bca = bias16(cx, cy, ax, ay);
        float16 wa = zb * zc, wb = za * zc, wc = za * zb, num = convert_float16(area) * za * wa;
        int16 ok = work & (area != 0);
        uint zbits[4][LANES16], at[4][LANES16], covered[4];
        for (int c = 0; c < 4; ++c)
            covered[c] = tiny_candidate(c, row, col, xs0, xs1, ys0, ys1, W, ax, ay, bx, by, cx, cy,
                                        bab, bbc, bca, wa, wb, wc, num, ok, zbits[c], at[c]);
        /* merge the covered candidates (lanes of each bit mask, lowest first) */
        for (int c = 0; c < 4; ++c)
            for (uint m = covered[c]; m; m &= m - 1) {
                int l = 31 - clz(m & (0u - m));
                global ulong *p = kv + at[c][l];
#ifdef UCAD_COUNT_COVERAGE
                *p += 1;
#else
                *p = min(*p, upsample(zbits[c][l], f0 + l));
#endif
            }
        for (uint m = others; m; m &= m - 1)
            raster_face(verts, faces, P, pverts, n_verts, prm, f0 + 31 - clz(m & (0u - m)), view,
                        0, 1, MODE_OWNER, keys, 0, 0);
    }
#ifndef UCAD_COUNT_COVERAGE
    for (uint g = 0; g < npix; ++g)
        resolve_key(kv[g], face_material, view * npix + g, tri_id, mat_id, depth);
#endif
}

/* Keys -> triangle id, material id (= face material + 1, 0 background), depth (+inf background). */
kernel void resolve_maps(global const ulong *keys, global const ushort *face_material,
                         global uint *tri_id, global ushort *mat_id, global float *depth, uint n) {
    uint g = get_global_id(0);
    if (g >= n) return;
    resolve_key(keys[g], face_material, g, tri_id, mat_id, depth);
}
