/* raster_serial.cl: the serial raster path (CPU devices), one work-item per view; one program
 * with raster_common.h.
 *
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
 * expression); only covered candidates are then merged, lane by lane, by a plain min. A
 * "medium" face (not clipped, not tiny, at most MEDIUM_CELLS = 16 centres in its box: 17 % of
 * the pairs of a 50k-triangle vehicle at 256 px, median 6 centres) is queued, and every 16
 * queued faces are drawn together the same way, each lane walking its own box
 * (draw_medium16): 144 views of such a vehicle measured ~121 -> ~100 ms on one PoCL thread,
 * against one face at a time through raster_face. Any other face (clipped, or a larger box)
 * goes through raster_face (MODE_OWNER). Output is the parallel path's, bit for bit, and
 * depends on no thread count: each view is one work-item's sequential loop, and the min of keys
 * does not depend on the order faces are drawn in. (On a GPU, one work-item per view would leave
 * the device nearly idle; the parallel path is the one for it.)
 */
#include "raster_common.h"

#define LANES16 16
/* GATHER16 (common.h): 16-lane gathers with int offsets (see above) */

/* resolve_key (raster_common.h) for the 16 keys at p, written at pixels g .. g + 15 */
static inline void resolve16(global const ulong *p, global const ushort *face_material, uint g,
                             global uint *tri_id, global ushort *mat_id, global float *depth) {
    ulong16 k = vload16(0, p);
    int16 bg = convert_int16(k == (ulong16)0xFFFFFFFFFFFFFFFFUL);
    uint16 t = bg ? (uint16)UCAD_BG_TRI : convert_uint16(k & 0xFFFFFFFFUL);
    uint16 fm = (uint16)(0);
    if (!all(bg)) {
        uint16 ti = bg ? (uint16)0 : t;
        fm = GATHER16(uint16, face_material, ti);
    }
    vstore16(t, 0, tri_id + g);
    vstore16(convert_ushort16(bg ? (uint16)UCAD_BG_MAT : fm + 1), 0, mat_id + g);
    vstore16(bg ? (float16)INFINITY : as_float16(convert_uint16(k >> 32)), 0, depth + g);
}

/* round_even (raster_common.h), 16 lanes */
static inline float16 round_even16(float16 x) {
    const float magic = 12582912.0f;
    return (x + magic) - magic;
}

/* project_vertices (raster_common.h) for the serial path: 16 consecutive vertices of one view per
 * work-item, in explicit 16-lane vectors, with the same expressions in the same order (hence the
 * same bits: no contraction, correctly rounded division, round_even); depths always stored.
 * PoCL left the scalar kernel unvectorized ("instruction return type cannot be vectorized"):
 * 144 views of a 25k-vertex mesh took ~14 ms. A last partial group goes through the scalar
 * project_vertex. Global size: (ceil(n_verts / 16), views). */
kernel void project_vertices16(global const float *verts, global const float *P,
                               raster_params prm, uint n_verts, global int2 *out,
                               global float *depth_out) {
    uint v0 = get_global_id(0) * LANES16, view = get_global_id(1);
    if (v0 >= n_verts || view >= (uint)prm.n_views) return;
    global const float *Pv = P + 12 * view;
    long at = (long)view * n_verts + v0;
    if (v0 + LANES16 > n_verts) {
        for (uint v = v0; v < n_verts; ++v)
            project_vertex(verts, Pv, prm, v, at + (v - v0), out, depth_out, 1);
        return;
    }
    const int16 i3 = (int16)(0, 3, 6, 9, 12, 15, 18, 21, 24, 27, 30, 33, 36, 39, 42, 45);
    global const float *src = verts + 3 * (long)v0;
    float16 x = GATHER16(float16, src, i3), y = GATHER16(float16, src + 1, i3);
    float16 z = GATHER16(float16, src + 2, i3);
    float16 u = Pv[0] * x + Pv[1] * y + Pv[2] * z + Pv[3];   /* as project() */
    float16 v = Pv[4] * x + Pv[5] * y + Pv[6] * z + Pv[7];
    float16 w = Pv[8] * x + Pv[9] * y + Pv[10] * z + Pv[11];
    float W = (float)prm.width, H = (float)prm.height;
    int16 code = ((w - prm.near >= 0.0f) ? (int16)0 : (int16)1)
               | ((u + GUARD * w >= 0.0f) ? (int16)0 : (int16)2)
               | (((W + GUARD) * w - u >= 0.0f) ? (int16)0 : (int16)4)
               | ((v + GUARD * w >= 0.0f) ? (int16)0 : (int16)8)
               | (((H + GUARD) * w - v >= 0.0f) ? (int16)0 : (int16)16);
    float16 s = 256.0f / w;                                    /* as snap() */
    /* integral values of magnitude <= 2^22 where code is 0: exact as int */
    int16 sx = convert_int16(round_even16(u * s)), sy = convert_int16(round_even16(v * s));
    int16 clipped = code != 0;
    int16 ox = clipped ? (int16)CLIPPED : sx, oy = clipped ? code : sy;
    global int *o = (global int *)(out + at);
    vstore16(shuffle2(ox, oy, (uint16)(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23)),
             0, o);
    vstore16(shuffle2(ox, oy, (uint16)(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15,
                                       31)), 1, o);
    vstore16(w, 0, depth_out + at);
}

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

/* raster_triangle32's setup for 16 faces at once, from their snapped corners q and depths z
 * and the first pixel centre of each box (xs0, ys0): canonical rotation (first the vertex
 * with the smallest (y, x); keeps the winding), coordinates relative to that pixel centre,
 * positive winding (b and c swapped), the edge biases and the depth weights, with
 * raster_triangle32's expressions. Lanes outside `use` get zero coordinates (zero area), so
 * no lane's arithmetic can overflow. */
typedef struct {
    int16 ax, ay, bx, by, cx, cy, area, bab, bbc, bca;
    float16 wa, wb, wc, num;
} setup16;

static inline setup16 face_setup16(int16 q0x, int16 q0y, int16 q1x, int16 q1y, int16 q2x,
                                   int16 q2y, float16 z0, float16 z1, float16 z2, int16 xs0,
                                   int16 ys0, int16 use) {
    setup16 t;
    int16 r1 = (q1y < q0y) | ((q1y == q0y) & (q1x < q0x));
    int16 rx = r1 ? q1x : q0x, ry = r1 ? q1y : q0y;
    int16 r2 = (q2y < ry) | ((q2y == ry) & (q2x < rx));
    int16 ax = r2 ? q2x : (r1 ? q1x : q0x), ay = r2 ? q2y : (r1 ? q1y : q0y);
    int16 bx = r2 ? q0x : (r1 ? q2x : q1x), by = r2 ? q0y : (r1 ? q2y : q1y);
    int16 cx = r2 ? q1x : (r1 ? q0x : q2x), cy = r2 ? q1y : (r1 ? q0y : q2y);
    float16 za = r2 ? z2 : (r1 ? z1 : z0), zb = r2 ? z0 : (r1 ? z2 : z1);
    float16 zc = r2 ? z1 : (r1 ? z0 : z2);
    int16 ox = xs0 * (int)SUB_ONE + (int)SUB_HALF, oy = ys0 * (int)SUB_ONE + (int)SUB_HALF;
    ax = use ? ax - ox : 0; ay = use ? ay - oy : 0;
    bx = use ? bx - ox : 0; by = use ? by - oy : 0;
    cx = use ? cx - ox : 0; cy = use ? cy - oy : 0;
    int16 area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax);
    int16 neg = area < 0;   /* make the winding positive: swap b and c */
    t.ax = ax; t.ay = ay;
    t.bx = neg ? cx : bx; t.by = neg ? cy : by;
    t.cx = neg ? bx : cx; t.cy = neg ? by : cy;
    float16 zb2 = neg ? zc : zb, zc2 = neg ? zb : zc;
    t.area = neg ? -area : area;
    t.bab = bias16(t.ax, t.ay, t.bx, t.by);
    t.bbc = bias16(t.bx, t.by, t.cx, t.cy);
    t.bca = bias16(t.cx, t.cy, t.ax, t.ay);
    t.wa = zb2 * zc2; t.wb = za * zc2; t.wc = za * zb2;
    t.num = convert_float16(t.area) * za * t.wa;
    return t;
}

/* raster_triangle32's edge functions E_ab, E_bc, E_ca of 16 faces set up by face_setup16, at
 * the pixel centres (dx, dy) relative to each box's first centre (into e); the mask of the lanes
 * of `use` whose centre the face covers (top-left rule: biases of the edges not owned). */
static inline uint cover16(const setup16 *t, int16 dx, int16 dy, int16 use, int16 *e) {
    int16 px = dx * (int)SUB_ONE, py = dy * (int)SUB_ONE;
    e[0] = (t->bx - t->ax) * (py - t->ay) - (t->by - t->ay) * (px - t->ax);
    e[1] = (t->cx - t->bx) * (py - t->by) - (t->cy - t->by) * (px - t->bx);
    e[2] = (t->ax - t->cx) * (py - t->cy) - (t->ay - t->cy) * (px - t->cx);
    return lane_mask(use & (e[0] + t->bab >= 0) & (e[1] + t->bbc >= 0) & (e[2] + t->bca >= 0));
}

/* The depth at those centres from their edge functions e (cover16), as raster_triangle32:
 * z = area / (E_bc / za + E_ca / zb + E_ab / zc) without per-vertex reciprocals. */
static inline float16 depth16(const setup16 *t, const int16 *e) {
    float16 den = convert_float16(e[1]) * t->wa + convert_float16(e[2]) * t->wb +
                  convert_float16(e[0]) * t->wc;
    return t->num / den;
}

/* Candidate c (0..3) of 16 tiny triangles: the c-th pixel centre of a row (row lanes), of a
 * column (col lanes) or of the 2 x 2 box (other lanes), from the box's first centre (xs0, ys0).
 * Stores its depth bits and its pixel index in the view, and returns the mask of the lanes that
 * cover it (ok set, centre inside the box and inside the triangle); other lanes' values are
 * meaningless. */
static inline uint tiny_candidate(int c, int16 row, int16 col, int16 xs0, int16 xs1, int16 ys0,
                                  int16 ys1, int W, const setup16 *t, int16 ok, uint *zbits,
                                  uint *at) {
    int16 dx = row ? (int16)c : col ? (int16)0 : (int16)(c & 1);
    int16 dy = row ? (int16)0 : col ? (int16)c : (int16)(c >> 1);
    int16 e[3];
    uint m = cover16(t, dx, dy, ok & (xs0 + dx <= xs1) & (ys0 + dy <= ys1), e);
    vstore16(as_uint16(depth16(t, e)), 0, zbits);
    vstore16(as_uint16((ys0 + dy) * W + xs0 + dx), 0, at);
    return m;
}

#define MEDIUM_CELLS 16
/* 16 unclipped faces whose boxes hold at most MEDIUM_CELLS pixel centres (lanes set in live),
 * drawn as raster_triangle32 draws them (same canonical rotation, origin, winding, biases, edge
 * functions and depth expression, so the same keys): each lane walks its own box row by row,
 * one centre per step, for as many steps as the largest box has centres. */
static void draw_medium16(uint16 face, int16 live, global const uint *face_a,
                          global const uint *face_b, global const uint *face_c,
                          global const int *pv, global const float *zv, int W, int H,
                          global ulong *kv) {
    uint16 i0 = GATHER16(uint16, face_a, face), i1 = GATHER16(uint16, face_b, face);
    uint16 i2 = GATHER16(uint16, face_c, face);
    uint16 x0i = 2 * i0, x1i = 2 * i1, x2i = 2 * i2;
    uint16 y0i = x0i + 1, y1i = x1i + 1, y2i = x2i + 1;
    int16 q0x = GATHER16(int16, pv, x0i), q1x = GATHER16(int16, pv, x1i);
    int16 q2x = GATHER16(int16, pv, x2i), q0y = GATHER16(int16, pv, y0i);
    int16 q1y = GATHER16(int16, pv, y1i), q2y = GATHER16(int16, pv, y2i);
    float16 z0 = GATHER16(float16, zv, i0), z1 = GATHER16(float16, zv, i1);
    float16 z2 = GATHER16(float16, zv, i2);
    int16 xs0, xs1, ys0, ys1;
    span16(min(q0x, min(q1x, q2x)), max(q0x, max(q1x, q2x)), W, &xs0, &xs1);
    span16(min(q0y, min(q1y, q2y)), max(q0y, max(q1y, q2y)), H, &ys0, &ys1);
    int16 nx = xs1 - xs0, ny = ys1 - ys0;
    setup16 t = face_setup16(q0x, q0y, q1x, q1y, q2x, q2y, z0, z1, z2, xs0, ys0, live);
    int16 ok = live & (t.area != 0);
    int16 cells = ok ? (nx + 1) * (ny + 1) : (int16)0;
    int8 c8 = max(cells.lo, cells.hi);
    int4 c4 = max(c8.lo, c8.hi);
    int2 c2 = max(c4.lo, c4.hi);
    int steps = max(c2.x, c2.y);
    int16 dx = 0, dy = 0;   /* the lane's current centre, relative to its box's first */
    for (int s = 0; s < steps; ++s) {
        int16 e[3];
        uint m = cover16(&t, dx, dy, ok & (dy <= ny), e);
        if (m) {
            uint zbits[LANES16], at[LANES16], ids[LANES16];
            vstore16(as_uint16(depth16(&t, e)), 0, zbits);
            vstore16(as_uint16((ys0 + dy) * W + xs0 + dx), 0, at);
            vstore16(face, 0, ids);
            for (; m; m &= m - 1) {
                int l = 31 - clz(m & (0u - m));
                global ulong *p = kv + at[l];
#ifdef UCAD_COUNT_COVERAGE
                *p += 1;
#else
                *p = min(*p, upsample(zbits[l], ids[l]));
#endif
            }
        }
        int16 wrap = dx >= nx;   /* next centre: along the row, then the next row */
        dx = wrap ? (int16)0 : dx + 1;
        dy = wrap ? dy + 1 : dy;
    }
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
    uint g0 = 0;   /* 16 keys at a time (PoCL does not vectorize these loops), then the tail */
    for (; g0 + LANES16 <= npix; g0 += LANES16) vstore16((ulong16)0xFFFFFFFFFFFFFFFFUL, 0, kv + g0);
    for (uint g = g0; g < npix; ++g) kv[g] = 0xFFFFFFFFFFFFFFFFUL;
#endif

    const uint16 lane = (uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    uint queue[2 * LANES16];   /* medium faces waiting to be drawn 16 at a time */
    int queued = 0;
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
        /* medium: unclipped, not tiny, at most MEDIUM_CELLS centres in its box: queued, drawn 16
         * faces at a time by draw_medium16 */
        int16 medium = live & ~tiny & ~clipped & ((nx + 1) * (ny + 1) <= MEDIUM_CELLS);
        for (uint m = lane_mask(medium); m; m &= m - 1)
            queue[queued++] = f0 + 31 - clz(m & (0u - m));
        if (queued >= LANES16) {
            draw_medium16(vload16(0, queue), (int16)(-1), face_a, face_b, face_c, pv, zv, W, H,
                          kv);
            queued -= LANES16;
            for (int k = 0; k < queued; ++k) queue[k] = queue[LANES16 + k];
        }
        uint others = lane_mask(live & ~tiny & ~medium);
        if (!others && !lane_mask(work)) continue;   /* no lane covers a pixel centre */
        float16 z0 = GATHER16(float16, zv, i0), z1 = GATHER16(float16, zv, i1);
        float16 z2 = GATHER16(float16, zv, i2);
        /* relative to the box's first pixel centre, as raster_triangle32 */
        setup16 t = face_setup16(q0x, q0y, q1x, q1y, q2x, q2y, z0, z1, z2, xs0, ys0, work);
        int16 ok = work & (t.area != 0);
        uint zbits[4][LANES16], at[4][LANES16], covered[4];
        for (int c = 0; c < 4; ++c)
            covered[c] = tiny_candidate(c, row, col, xs0, xs1, ys0, ys1, W, &t, ok, zbits[c],
                                        at[c]);
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
    if (queued) {   /* the last queued faces; padding lanes repeat the first and draw nothing */
        for (int k = queued; k < LANES16; ++k) queue[k] = queue[0];
        draw_medium16(vload16(0, queue), convert_int16(lane) < queued, face_a, face_b, face_c, pv,
                      zv, W, H, kv);
    }
#ifndef UCAD_COUNT_COVERAGE
    uint g1 = 0;
    for (; g1 + LANES16 <= npix; g1 += LANES16)
        resolve16(kv + g1, face_material, view * npix + g1, tri_id, mat_id, depth);
    for (uint g = g1; g < npix; ++g)
        resolve_key(kv[g], face_material, view * npix + g, tri_id, mat_id, depth);
#endif
}
