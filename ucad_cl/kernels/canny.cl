/* canny.cl: Canny edge detection over a batch of equally sized uint8 images, bit-exact with
 * OpenCV's cv::Canny(src, dst, low, high, apertureSize = 3, L2gradient).
 *
 * Layout. Images are (B, H, W) uint8 planes; colour images (B, H, W, 3) are first split into
 * (B, 3, H, W) planes by canny_planes (or made from id maps and a colour table by
 * canny_id_planes). The map/output is (B, H, W). The batch is the last NDRange
 * dimension (the only one for the trace). Build options: -DCANNY_CHANNELS=1|3, -DCANNY_L2=0|1,
 * -DCANNY_ROWS=rows per work-item (one program per combination, cached by the host).
 *
 * Passes (one launch each for the whole batch):
 *   canny_gradient_nms  Sobel 3x3 with replicated borders on every channel (|dx|, |dy| <= 1020),
 *                       magnitude |dx| + |dy| (L1, 16-bit lanes) or dx*dx + dy*dy (L2, 32-bit);
 *                       with 3 channels the channel of largest magnitude wins, the first one on
 *                       ties (OpenCV's rule). The NMS direction follows OpenCV's fixed point
 *                       tan(22.5 deg) = TG22 / 2^15, computed exactly in 16-bit lanes. Then
 *                       non-maximum suppression with OpenCV's comparisons (strict on the
 *                       "previous" side, >= on the "next" side for horizontal and vertical
 *                       directions, strict on both sides for diagonals; magnitudes outside the
 *                       image count as 0) and the thresholds. Writes the map 0 = no edge,
 *                       1 = weak (m > low), 2 = strong (m > high). No gradient buffer: each
 *                       work-item owns a 16-pixel-wide, CANNY_ROWS-tall strip and rolls the
 *                       horizontal Sobel factors and magnitudes of three rows down it.
 *   canny_trace         hysteresis: one work-item per image with a depth-first worklist; every
 *                       weak or strong pixel 8-connected to a strong pixel through such pixels
 *                       becomes an edge (3). The set is a unique fixed point, so the visiting order
 *                       (scan top-down, left to right, last-in-first-out stack) cannot change the
 *                       result. The same work-item then writes 255 for edges, 0 elsewhere, in place.
 *
 * Thresholds arrive as the integers OpenCV compares against (see ucad_cl/edges.py): a pixel is a
 * candidate when m > low and strong when m > high (L2: squared thresholds).
 */
#include "common.h"

#ifndef CANNY_CHANNELS
#define CANNY_CHANNELS 1
#endif
#ifndef CANNY_L2
#define CANNY_L2 0
#endif
#ifndef CANNY_ROWS
#define CANNY_ROWS 32
#endif

/* (int)(tan(22.5 deg) * 2^15 + 0.5), as OpenCV. */
#define TG22 13573

#define DIR_HORIZONTAL 0    /* compare left / right */
#define DIR_VERTICAL 1      /* compare up / down */
#define DIR_DIAG_MAIN 2     /* dx, dy of the same sign: up-left / down-right */
#define DIR_DIAG_ANTI 3     /* opposite signs: up-right / down-left */

#define MAP_NONE 0
#define MAP_WEAK 1
#define MAP_STRONG 2
#define MAP_EDGE 3

#define VSPAN 16            /* pixels per work-item along x (one 16-lane vector) */
#define INLINE __attribute__((always_inline))   /* so `fast` is a constant at each call site */

typedef struct {
    int width, height, n_images, channels;
    int low, high;          /* OpenCV's integer thresholds (already squared for L2) */
    int l2;                 /* 0: |dx| + |dy|, 1: dx*dx + dy*dy (must match -DCANNY_L2) */
    int pad;
} canny_params;

/* Magnitudes fit 16 bits for L1 (<= 2040), need 32 for L2 (< 2^21). Sobel sums are shorts. */
#if CANNY_L2
typedef int16 mag_t;
#define TO_MAG(v) convert_int16(v)
#define TO_SHORT_MASK(m) convert_short16(m)
#else
typedef short16 mag_t;
#define TO_MAG(v) convert_short16(v)
#define TO_SHORT_MASK(m) (m)
#endif

/* 16 pixels x .. x+15 of a plane row of width W; `fast` (x >= 0 and x + 16 <= W, known at the
 * call site) is a plain vector load, otherwise columns are clamped into [0, W) (the replicated
 * border). */
static inline INLINE short16 load16(global const uchar *row, int x, int W, const int fast) {
    if (fast) return convert_short16(vload16(0, row + x));
    short lanes[VSPAN];
    for (int i = 0; i < VSPAN; ++i) lanes[i] = row[clamp(x + i, 0, W - 1)];
    return vload16(0, lanes);
}

/* Horizontal Sobel factors of one row at column shifts -1, 0, +1 of a span:
 * smooth s = a[-1] + 2 a[0] + a[1] and difference d = a[1] - a[-1]. */
typedef struct { short16 s0, s1, s2, d0, d1, d2; } hrow;

static inline INLINE hrow hfilter(global const uchar *plane, int r, int H, int W, int x0, const int fast) {
    global const uchar *row = plane + clamp(r, 0, H - 1) * W;      /* replicated border rows */
    const short16 a0 = load16(row, x0 - 2, W, fast), a1 = load16(row, x0 - 1, W, fast),
                  a2 = load16(row, x0, W, fast), a3 = load16(row, x0 + 1, W, fast),
                  a4 = load16(row, x0 + 2, W, fast);
    hrow h;
    h.s0 = a0 + a1 + a1 + a2; h.s1 = a1 + a2 + a2 + a3; h.s2 = a2 + a3 + a3 + a4;
    h.d0 = a2 - a0;          h.d1 = a3 - a1;          h.d2 = a4 - a2;
    return h;
}

/* |x| as compare + blend (PoCL's abs() for short16 is split into 2-lane pieces: slow). */
static inline INLINE short16 abs16(short16 x) { return select(x, -x, x < (short16)0); }
static inline INLINE mag_t max16(mag_t a, mag_t b) { return select(a, b, b > a); }

static inline INLINE mag_t magnitude(short16 dx, short16 dy) {
#if CANNY_L2
    const int16 x = convert_int16(dx), y = convert_int16(dy);
    return x * x + y * y;
#else
    return abs16(dx) + abs16(dy);
#endif
}

/* Zero the magnitudes of columns outside the image, classify the direction of (bdx, bdy). */
static inline INLINE void finish_gradient_row(mag_t b0, mag_t b1, mag_t b2, short16 bdx,
                                              short16 bdy, int x0, int W, const int fast,
                                              mag_t *ml, mag_t *mc, mag_t *mr, mag_t *dir) {
    if (!fast || x0 + VSPAN + 1 > W) {            /* columns outside the image count as 0 */
        const int16 col = (int16)x0 + (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        b0 = select(b0, (mag_t)0, TO_MAG(col - 1 < 0 | col - 1 >= W));
        b1 = select(b1, (mag_t)0, TO_MAG(col >= W));
        b2 = select(b2, (mag_t)0, TO_MAG(col + 1 >= W));
    }
    *ml = b0; *mc = b1; *mr = b2;
    /* classify_direction in 16-bit lanes, exactly: with a = |dx|, b = |dy| (<= 1020) and
     * a * 27146 = q * 2^16 + r (27146 = 2 * TG22),
     *   y < tg22x  <=>  b * 2^16 < a * 27146        <=>  b < q or (b == q and r > 0),
     *   y > tg67x  <=>  (b - 2a) * 2^16 > a * 27146  <=>  b - 2a > q. */
    const ushort16 a = as_ushort16(abs16(bdx)), bb = as_ushort16(abs16(bdy));
    const ushort16 q = mul_hi(a, (ushort16)(2 * TG22)), r = a * (ushort16)(2 * TG22);
    const short16 horiz = (bb < q) | ((bb == q) & (r != (ushort16)0));
    const short16 vert = (as_short16(bb) - as_short16(a) - as_short16(a)) > as_short16(q);
    const short16 diag = select((short16)DIR_DIAG_MAIN, (short16)DIR_DIAG_ANTI, (bdx ^ bdy) < (short16)0);
    *dir = TO_MAG(select(select(diag, (short16)DIR_VERTICAL, vert), (short16)DIR_HORIZONTAL, horiz));
}

/* One channel's Sobel from the horizontal factors of the rows above (u), at (c), below (d):
 * magnitudes at shifts -1, 0, +1 and (dx, dy) at shift 0. */
static inline INLINE void channel_gradients(hrow u, hrow c, hrow d, mag_t *g0, mag_t *g1,
                                            mag_t *g2, short16 *dx, short16 *dy) {
    *g0 = magnitude(u.d0 + c.d0 + c.d0 + d.d0, d.s0 - u.s0);
    *dx = u.d1 + c.d1 + c.d1 + d.d1;
    *dy = d.s1 - u.s1;
    *g1 = magnitude(*dx, *dy);
    *g2 = magnitude(u.d2 + c.d2 + c.d2 + d.d2, d.s2 - u.s2);
}

/* Grey gradient row from rolled factors: magnitudes at columns x0-1+i, x0+i, x0+1+i (0 outside
 * the image) and direction at x0+i. */
static inline INLINE void gradient_row(hrow u, hrow c, hrow d, int x0, int W, const int fast,
                                       mag_t *ml, mag_t *mc, mag_t *mr, mag_t *dir) {
    mag_t g0, g1, g2;
    short16 dx, dy;
    channel_gradients(u, c, d, &g0, &g1, &g2, &dx, &dy);
    finish_gradient_row(g0, g1, g2, dx, dy, x0, W, fast, ml, mc, mr, dir);
}

/* Gradient row y computed straight from the three source rows of every channel, one channel
 * at a time (no state carried between rows: for colour images, rolling three rows of factors
 * for three channels would not fit the vector registers). Same outputs as gradient_row. */
static inline INLINE void gradient_row_direct(global const uchar *planes, int y, int H, int W,
                                              int x0, const int fast, mag_t *ml, mag_t *mc,
                                              mag_t *mr, mag_t *dir) {
    mag_t b0 = 0, b1 = 0, b2 = 0, g0, g1, g2;
    short16 bdx = 0, bdy = 0, dx, dy;
    for (int k = 0; k < CANNY_CHANNELS; ++k) {
        global const uchar *plane = planes + (size_t)k * W * H;
        channel_gradients(hfilter(plane, y - 1, H, W, x0, fast), hfilter(plane, y, H, W, x0, fast),
                          hfilter(plane, y + 1, H, W, x0, fast), &g0, &g1, &g2, &dx, &dy);
        if (k == 0) {
            b0 = g0; b1 = g1; b2 = g2; bdx = dx; bdy = dy;
        } else {                                  /* strictly larger wins: first channel on ties */
            b0 = max16(b0, g0); b2 = max16(b2, g2);
            const short16 wins = TO_SHORT_MASK(g1 > b1);
            b1 = max16(b1, g1); bdx = select(bdx, dx, wins); bdy = select(bdy, dy, wins);
        }
    }
    finish_gradient_row(b0, b1, b2, bdx, bdy, x0, W, fast, ml, mc, mr, dir);
}

/* NMS + thresholds of rows y0 .. y1-1 of one 16-pixel span (see canny_gradient_nms). The
 * magnitudes of three rows roll down with y (grey: the horizontal factors of three rows too). */
static inline INLINE void span_nms(global const uchar *planes, global uchar *out, int W, int H, int x0,
                            int y0, int y1, int low, int high, const int fast) {
    mag_t pl = 0, pc = 0, pr = 0, pd = 0, cl, cc, cr, cd, nl, nc, nr, nd;
#if CANNY_CHANNELS == 1
    hrow hu = hfilter(planes, y0 - 2, H, W, x0, fast), hc = hfilter(planes, y0 - 1, H, W, x0, fast),
         hd = hfilter(planes, y0, H, W, x0, fast);               /* factors for gradient row y0 - 1 */
    if (y0 >= 1) gradient_row(hu, hc, hd, x0, W, fast, &pl, &pc, &pr, &pd);
    hu = hc; hc = hd; hd = hfilter(planes, y0 + 1, H, W, x0, fast);   /* -> gradient row y0 */
    gradient_row(hu, hc, hd, x0, W, fast, &cl, &cc, &cr, &cd);
#else
    if (y0 >= 1) gradient_row_direct(planes, y0 - 1, H, W, x0, fast, &pl, &pc, &pr, &pd);
    gradient_row_direct(planes, y0, H, W, x0, fast, &cl, &cc, &cr, &cd);
#endif
#if CANNY_L2
    const mag_t lowv = (mag_t)low, highv = (mag_t)high;
#else
    const mag_t lowv = (mag_t)(short)clamp(low, -1, 32767), highv = (mag_t)(short)clamp(high, -1, 32767);
#endif
    for (int y = y0; y < y1; ++y) {
        if (y + 1 < H) {
#if CANNY_CHANNELS == 1
            hu = hc; hc = hd; hd = hfilter(planes, y + 2, H, W, x0, fast);   /* -> row y + 1 */
            gradient_row(hu, hc, hd, x0, W, fast, &nl, &nc, &nr, &nd);
#else
            gradient_row_direct(planes, y + 1, H, W, x0, fast, &nl, &nc, &nr, &nd);
#endif
        } else {
            nl = nc = nr = nd = 0;
        }
        const mag_t horiz = cd == (mag_t)DIR_HORIZONTAL, vert = cd == (mag_t)DIR_VERTICAL;
        const mag_t anti = cd == (mag_t)DIR_DIAG_ANTI;
        const mag_t prev = select(select(select(pl, pr, anti), pc, vert), cl, horiz);
        const mag_t next = select(select(select(nr, nl, anti), nc, vert), cr, horiz);
        /* previous side strict; next side >= for horizontal / vertical, > for diagonals */
        const mag_t keep = (cc > lowv) & (cc > prev) & select(cc > next, cc >= next, horiz | vert);
        const uchar16 code = convert_uchar16(select(
            (mag_t)MAP_NONE, select((mag_t)MAP_WEAK, (mag_t)MAP_STRONG, cc > highv), keep));
        if (x0 + VSPAN <= W) {
            vstore16(code, 0, out + y * W + x0);
        } else {
            uchar lanes[VSPAN];
            vstore16(code, 0, lanes);
            for (int i = 0; x0 + i < W; ++i) out[y * W + x0 + i] = lanes[i];
        }
        pl = cl; pc = cc; pr = cr; pd = cd;
        cl = nl; cc = nc; cr = nr; cd = nd;
    }
}

/* (B, H, W, 3) interleaved -> (B, 3, H, W) planes. One work-item per VSPAN pixels of a row:
 * global (ceil(W / VSPAN), H, B). Only used with CANNY_CHANNELS == 3. */
kernel void canny_planes(global const uchar *src, const canny_params p, global uchar *planes) {
    const int x0 = get_global_id(0) * VSPAN, y = get_global_id(1), b = get_global_id(2);
    const int W = p.width, H = p.height;
    if (x0 >= W || y >= H) return;
    const size_t n = (size_t)W * H, i0 = (size_t)y * W + x0;
    global const uchar *s = src + ((size_t)b * n + i0) * 3;
    global uchar *d = planes + (size_t)b * 3 * n + i0;
    const int count = min(VSPAN, W - x0);
    for (int i = 0; i < count; ++i) {
        d[i] = s[3 * i]; d[n + i] = s[3 * i + 1]; d[2 * n + i] = s[3 * i + 2];
    }
}

/* (B, H, W) uint16 ids -> (B, 3, H, W) planes of the colours lut[id] (RGB in the low 3 bytes,
 * R lowest): the colour image of a material-id map without building it on the host. Same
 * NDRange as canny_planes; only used with CANNY_CHANNELS == 3. */
kernel void canny_id_planes(global const ushort *ids, global const uint *lut, const canny_params p,
                            global uchar *planes) {
    const int x0 = get_global_id(0) * VSPAN, y = get_global_id(1), b = get_global_id(2);
    const int W = p.width, H = p.height;
    if (x0 >= W || y >= H) return;
    const size_t n = (size_t)W * H, i0 = (size_t)y * W + x0;
    global const ushort *s = ids + (size_t)b * n + i0;
    global uchar *d = planes + (size_t)b * 3 * n + i0;
    const int count = min(VSPAN, W - x0);
    for (int i = 0; i < count; ++i) {
        const uint c = lut[s[i]];
        d[i] = (uchar)c; d[n + i] = (uchar)(c >> 8); d[2 * n + i] = (uchar)(c >> 16);
    }
}

/* planes: (B, C, H, W) (for C = 1 simply the images); map: (B, H, W).
 * Global (ceil(W / VSPAN), ceil(H / CANNY_ROWS), B). Strips whose loads (2 columns either side)
 * stay inside the image use plain vector loads; the others clamp columns lane by lane. */
kernel void canny_gradient_nms(global const uchar *planes, const canny_params p, global uchar *map) {
    const int x0 = get_global_id(0) * VSPAN, y0 = get_global_id(1) * CANNY_ROWS;
    const int b = get_global_id(2);
    const int W = p.width, H = p.height;
    if (x0 >= W || y0 >= H) return;
    const int y1 = min(y0 + CANNY_ROWS, H);
    global const uchar *img = planes + (size_t)b * H * W * CANNY_CHANNELS;
    global uchar *out = map + (size_t)b * H * W;
    if (x0 >= 2 && x0 + VSPAN + 2 <= W)
        span_nms(img, out, W, H, x0, y0, y1, p.low, p.high, 1);
    else
        span_nms(img, out, W, H, x0, y0, y1, p.low, p.high, 0);
}

/* Mark (r, c) as an edge and push it when it is weak or strong (not yet visited). */
#define VISIT(r, c)                                                             \
    do {                                                                        \
        int i_ = (r) * W + (c);                                                 \
        if (m[i_] == MAP_WEAK || m[i_] == MAP_STRONG) {                         \
            m[i_] = MAP_EDGE;                                                   \
            stack[top++] = ((r) << 16) | (c);                                   \
        }                                                                       \
    } while (0)

/* Depth-first flood from the strong pixel k over weak/strong 8-neighbours. */
static void trace_from(global uchar *m, global int *stack, int k, int W, int H) {
    int top = 0;
    const int r0 = k / W, c0 = k - r0 * W;
    VISIT(r0, c0);
    while (top > 0) {
        const int q = stack[--top];
        const int r = q >> 16, c = q & 0xFFFF;
        const int rl = max(r - 1, 0), rh = min(r + 1, H - 1);
        const int cl = max(c - 1, 0), ch = min(c + 1, W - 1);
        for (int rr = rl; rr <= rh; ++rr)
            for (int cc = cl; cc <= ch; ++cc) VISIT(rr, cc);
    }
}

/* One work-item per image: global (B,). stack: (B, H*W) ints (row << 16 | column), scratch.
 * Strong pixels are found 16 bytes at a time; the map is then turned into 255 / 0 in place. */
kernel void canny_trace(global uchar *map, const canny_params p, global int *stack_all) {
    const int b = get_global_id(0);
    if (b >= p.n_images) return;
    const int W = p.width, H = p.height, n = W * H;
    global uchar *m = map + (size_t)b * n;
    global int *stack = stack_all + (size_t)b * n;
    int i = 0;
    for (; i + 16 <= n; i += 16) {
        const uchar16 v = vload16(0, m + i);
        if (!any(as_char16(v == (uchar16)MAP_STRONG))) continue;
        for (int k = i; k < i + 16; ++k)
            if (m[k] == MAP_STRONG) trace_from(m, stack, k, W, H);
    }
    for (; i < n; ++i)
        if (m[i] == MAP_STRONG) trace_from(m, stack, i, W, H);
    int j = 0;
    for (; j + 16 <= n; j += 16) {
        const uchar16 v = vload16(0, m + j);
        vstore16(as_uchar16(v == (uchar16)MAP_EDGE), 0, m + j);
    }
    for (; j < n; ++j) m[j] = (m[j] == MAP_EDGE) ? 255 : 0;
}
