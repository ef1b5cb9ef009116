/* raster_common.h: what both raster paths share (raster_parallel.cl, raster_serial.cl): vertex
 * projection and clipping, fixed-point snapping, the exact triangle rasterizer, one face's
 * clip-and-draw (raster_face) and key resolution. Each path's .cl file includes it and is built
 * as its own program.
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
 * Work split. project_vertices (here): clip code and snapped position (and, for the serial path,
 * depth) of every (vertex, view), once. Then one of two paths, which give identical bytes (the
 * same keys, computed by the same expressions; tests/test_render.py checks it): parallel (GPUs,
 * raster_parallel.cl) and serial (CPUs, raster_serial.cl); see each file's header.
 *
 * BIG_PIXELS (from ucad_cl/abi.py, like every constant host and kernels share) bounds the boxes
 * the 32-bit rasterizer takes; UCAD_COUNT_COVERAGE (test builds) counts coverage instead.
 */
#ifndef UCAD_RASTER_COMMON_H
#define UCAD_RASTER_COMMON_H
#include "common.h"

#define SUB_BITS 8
#define SUB_ONE 256L
#define SUB_HALF 128L
#define GUARD 8192.0f
#define MAX_POLY 9

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
 * expression, same bits), which measured cheaper there than the extra bandwidth. The serial
 * path uses project_vertices16 (raster_serial.cl), the same in explicit 16-lane vectors. */
#define CLIPPED INT_MIN
static inline void project_vertex(global const float *verts, global const float *Pv,
                                  raster_params prm, uint v, long at, global int2 *out,
                                  global float *depth_out, uint store_depth) {
    float W = (float)prm.width, H = (float)prm.height;
    hvert h = project(Pv, verts[3 * v], verts[3 * v + 1], verts[3 * v + 2]);
    /* straight-line plane tests (same expressions as plane_dist) */
    int code = (!(h.w - prm.near >= 0.0f))
             | (!(h.u + GUARD * h.w >= 0.0f)) << 1
             | (!((W + GUARD) * h.w - h.u >= 0.0f)) << 2
             | (!(h.v + GUARD * h.w >= 0.0f)) << 3
             | (!((H + GUARD) * h.w - h.v >= 0.0f)) << 4;
    long2 sn = snap(h);
    if (store_depth) depth_out[at] = h.w;
    out[at] = code ? (int2)(CLIPPED, code) : (int2)((int)sn.x, (int)sn.y);
}

kernel void project_vertices(global const float *verts, global const float *P, raster_params prm,
                             uint n_verts, global int2 *out, global float *depth_out,
                             uint store_depth) {
    uint v = get_global_id(0), view = get_global_id(1);
    if (v >= n_verts || view >= (uint)prm.n_views) return;
    project_vertex(verts, P + 12 * view, prm, v, (long)view * n_verts + v, out, depth_out,
                   store_depth);
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

/* Key -> triangle id, material id (= face material + 1, UCAD_BG_MAT background), depth (+inf
 * background), at pixel g. */
static inline void resolve_key(ulong k, global const ushort *face_material, uint g,
                               global uint *tri_id, global ushort *mat_id, global float *depth) {
    int bg = k == 0xFFFFFFFFFFFFFFFFUL;
    uint t = (uint)(k & 0xFFFFFFFFUL);
    tri_id[g] = bg ? UCAD_BG_TRI : t;
    mat_id[g] = bg ? (ushort)UCAD_BG_MAT : (ushort)(face_material[bg ? 0 : t] + 1);
    depth[g] = bg ? INFINITY : as_float((uint)(k >> 32));
}

#endif
