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
 * Work split. raster_small: one work-item per (face, view). A triangle whose clipped bounding
 * box exceeds BIG_PIXELS pixels is appended to a list instead, and raster_big spreads each listed
 * triangle over LANES work-items (rows interleaved). If the list overflows, the host enlarges it
 * and reruns raster_small: atomic_min is idempotent, so a rerun only repeats work.
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

/* Snapped fixed-point position (1/256 px) of a vertex inside the guard band. */
static inline long2 snap(hvert p) {
    return (long2)(convert_long_rte(p.u / p.w * 256.0f), convert_long_rte(p.v / p.w * 256.0f));
}

/* Pixel range [lo, hi] whose centres lie in [a, b] (fixed point), clamped to [0, n-1]. */
static inline int2 pixel_span(long a, long b, int n) {
    long lo = a - SUB_HALF, hi = b - SUB_HALF;
    int2 r;
    r.x = lo <= 0 ? 0 : (int)((lo + SUB_ONE - 1) / SUB_ONE);
    r.y = hi < 0 ? -1 : (int)min(hi / SUB_ONE, (long)(n - 1));
    return r;
}

static inline int owned(long2 a, long2 b) {
    long dx = b.x - a.x, dy = b.y - a.y;
    return dy < 0 || (dy == 0 && dx > 0);
}

/* Rasterize one snapped triangle into one view's key map, rows row0, row0+step, ... */
static void raster_triangle(long2 p0, long2 p1, long2 p2, float z0, float z1, float z2,
                            uint face, int width, int height, int row0, int row_step,
                            global ulong *keys) {
    /* canonical rotation: smallest (y, x) first; keeps the winding */
    int r = 0;
    if (p1.y < p0.y || (p1.y == p0.y && p1.x < p0.x)) r = 1;
    long2 pr = r ? p1 : p0;
    if (p2.y < pr.y || (p2.y == pr.y && p2.x < pr.x)) r = 2;
    long2 a, b, c; float za, zb, zc;
    if (r == 0)      { a = p0; b = p1; c = p2; za = z0; zb = z1; zc = z2; }
    else if (r == 1) { a = p1; b = p2; c = p0; za = z1; zb = z2; zc = z0; }
    else             { a = p2; b = p0; c = p1; za = z2; zb = z0; zc = z1; }
    long area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
    if (area == 0) return;
    if (area < 0) {   /* make the winding positive (clockwise on screen, y down) */
        long2 t = b; b = c; c = t;
        float tz = zb; zb = zc; zc = tz;
        area = -area;
    }
    int2 xs = pixel_span(min(a.x, min(b.x, c.x)), max(a.x, max(b.x, c.x)), width);
    int2 ys = pixel_span(min(a.y, min(b.y, c.y)), max(a.y, max(b.y, c.y)), height);
    if (xs.x > xs.y || ys.x > ys.y) return;

    /* edge functions E_ab(P) = (b - a) x (P - a); bias -1 on edges that are not owned */
    long bias_ab = owned(a, b) ? 0 : -1;
    long bias_bc = owned(b, c) ? 0 : -1;
    long bias_ca = owned(c, a) ? 0 : -1;
    float iza = 1.0f / za, izb = 1.0f / zb, izc = 1.0f / zc;
    float farea = (float)area;
    long px0 = (long)xs.x * SUB_ONE + SUB_HALF;
    for (int i = ys.x + row0; i <= ys.y; i += row_step) {
        long py = (long)i * SUB_ONE + SUB_HALF;
        long e_ab = (b.x - a.x) * (py - a.y) - (b.y - a.y) * (px0 - a.x);
        long e_bc = (c.x - b.x) * (py - b.y) - (c.y - b.y) * (px0 - b.x);
        long e_ca = (a.x - c.x) * (py - c.y) - (a.y - c.y) * (px0 - c.x);
        long s_ab = -(b.y - a.y) * SUB_ONE, s_bc = -(c.y - b.y) * SUB_ONE,
             s_ca = -(a.y - c.y) * SUB_ONE;
        global ulong *row = keys + (long)i * width;
        for (int j = xs.x; j <= xs.y; ++j) {
            if (e_ab + bias_ab >= 0 && e_bc + bias_bc >= 0 && e_ca + bias_ca >= 0) {
                /* barycentric weight of a is E_bc / area, of b is E_ca / area, of c is E_ab / area */
                float inv = (float)e_bc * iza + (float)e_ca * izb + (float)e_ab * izc;
                float z = farea / inv;
#ifdef UCAD_COUNT_COVERAGE    /* test build: count how often each pixel centre is covered */
                (void)z;
                atom_add(row + j, 1UL);
#else
                ulong key = ((ulong)as_uint(z) << 32) | (ulong)face;
                atom_min(row + j, key);
#endif
            }
            e_ab += s_ab; e_bc += s_bc; e_ca += s_ca;
        }
    }
}

/* Clip one face against near plane + guard band and rasterize the pieces.
 * small_pass: if the clipped bounding box is bigger than BIG_PIXELS, push (face, view) instead.
 */
static void raster_face(global const float *verts, global const uint *faces,
                        global const float *P, raster_params prm, uint face, uint view,
                        int row0, int row_step, int small_pass,
                        global ulong *keys, global uint *big_list, volatile global uint *big_count) {
    float W = (float)prm.width, H = (float)prm.height;
    uint i0 = faces[3 * face], i1 = faces[3 * face + 1], i2 = faces[3 * face + 2];
    global const float *Pv = P + 12 * view;
    hvert poly[MAX_POLY], tmp[MAX_POLY];
    poly[0] = project(Pv, verts[3 * i0], verts[3 * i0 + 1], verts[3 * i0 + 2]);
    poly[1] = project(Pv, verts[3 * i1], verts[3 * i1 + 1], verts[3 * i1 + 2]);
    poly[2] = project(Pv, verts[3 * i2], verts[3 * i2 + 1], verts[3 * i2 + 2]);
    int n = 3;
    for (int k = 0; k < 5; ++k) {
        float d0 = plane_dist(poly[0], k, prm.near, W, H);
        float d1 = plane_dist(poly[1], k, prm.near, W, H);
        float d2 = plane_dist(poly[2], k, prm.near, W, H);
        if (d0 < 0.0f && d1 < 0.0f && d2 < 0.0f) return;        /* wholly outside one plane */
        if (!(d0 >= 0.0f && d1 >= 0.0f && d2 >= 0.0f)) n = 0;   /* needs clipping (or NaN) */
    }
    if (n == 0) {   /* Sutherland-Hodgman against the five planes */
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
    }
    long2 s[MAX_POLY];
    long xmin = LONG_MAX, xmax = LONG_MIN, ymin = LONG_MAX, ymax = LONG_MIN;
    for (int e = 0; e < n; ++e) {
        s[e] = snap(poly[e]);
        xmin = min(xmin, s[e].x); xmax = max(xmax, s[e].x);
        ymin = min(ymin, s[e].y); ymax = max(ymax, s[e].y);
    }
    if (small_pass) {
        int2 xs = pixel_span(xmin, xmax, prm.width), ys = pixel_span(ymin, ymax, prm.height);
        if (xs.x > xs.y || ys.x > ys.y) return;
        if ((long)(xs.y - xs.x + 1) * (long)(ys.y - ys.x + 1) > BIG_PIXELS) {
            uint slot = atomic_inc(big_count);
            if (slot < prm.big_capacity) { big_list[2 * slot] = face; big_list[2 * slot + 1] = view; }
            return;
        }
    }
    global ulong *kv = keys + (long)view * prm.width * prm.height;
    for (int e = 1; e + 1 < n; ++e)   /* fan: (0, e, e+1) */
        raster_triangle(s[0], s[e], s[e + 1], poly[0].w, poly[e].w, poly[e + 1].w,
                        face, prm.width, prm.height, row0, row_step, kv);
}

/* One work-item per (face = global id 0, view = global id 1). */
kernel void raster_small(global const float *verts, global const uint *faces, global const float *P,
                         raster_params prm, global ulong *keys,
                         global uint *big_list, volatile global uint *big_count) {
    uint face = get_global_id(0), view = get_global_id(1);
    if (face >= (uint)prm.n_faces || view >= (uint)prm.n_views) return;
    raster_face(verts, faces, P, prm, face, view, 0, 1, 1, keys, big_list, big_count);
}

/* One work-item per (listed triangle = global id 0, lane = global id 1 in [0, LANES)). */
kernel void raster_big(global const float *verts, global const uint *faces, global const float *P,
                       raster_params prm, global ulong *keys, global const uint *big_list, uint n_big) {
    uint entry = get_global_id(0), lane = get_global_id(1), lanes = get_global_size(1);
    if (entry >= n_big) return;
    raster_face(verts, faces, P, prm, big_list[2 * entry], big_list[2 * entry + 1], (int)lane,
                (int)lanes, 0, keys, 0, 0);
}

/* Keys -> triangle id, material id (= face material + 1, 0 background), depth (+inf background). */
kernel void resolve_maps(global const ulong *keys, global const ushort *face_material,
                         global uint *tri_id, global ushort *mat_id, global float *depth, uint n) {
    uint g = get_global_id(0);
    if (g >= n) return;
    ulong k = keys[g];
    if (k == 0xFFFFFFFFFFFFFFFFUL) {
        tri_id[g] = UCAD_BG_TRI; mat_id[g] = UCAD_BG_MAT; depth[g] = INFINITY;
    } else {
        uint t = (uint)(k & 0xFFFFFFFFUL);
        tri_id[g] = t;
        mat_id[g] = (ushort)(face_material[t] + 1);
        depth[g] = as_float((uint)(k >> 32));
    }
}
