/* features.cl: batched histogram-of-oriented-gradients pose descriptor.
 *
 * Input: B square RGB crops, uint8, (B, S, S, 3), row-major, already resized by the host.
 *
 * 1. hog_pixel_gradients, one work-item per (pixel, image), writes (magnitude, orientation
 *    position) per pixel; hog_cell_histograms, one work-item per (cell, image), sums the votes
 *    (split in two so the per-pixel part, atan2 included, vectorises across work-items).
 *    Per pixel, for each channel c the
 *    central differences gx = I(y, x+1) - I(y, x-1), gy = I(y+1, x) - I(y-1, x) in exact integer
 *    uint8 units (neighbours clamped to the image: replicate border); the channel with the largest
 *    gx^2 + gy^2 wins (ties: lowest channel), which makes the gradient insensitive to which
 *    colour the paint is. Magnitude m = sqrt(gx^2 + gy^2) / 255 - min_grad (soft threshold:
 *    pixels with m <= 0 do not vote; it removes sensor noise and smooth shading/backgrounds);
 *    orientation t = atan2(gy, gx) (same_bits_atan2: the same bits on every device), folded
 *    into [0, pi) (unsigned) or [0, 2 pi) (signed). Votes are split linearly between the two
 *    nearest bin centres (centre of bin k at (k + 0.5) * range / bins, cyclic); space is hard
 *    binned (pixel (y, x) goes to cell (y / CELL, x / CELL)). Pixels are visited in row-major
 *    order, so sums are bit-identical run to run.
 * 2. hog_block_normalise, one work-item per (block, image): blocks of 2x2 cells, stride one cell;
 *    the 4 * bins vector is L2-Hys normalised: v / sqrt(|v|^2 + eps^2), clipped at `clip`,
 *    renormalised the same way.
 * 3. hog_finalise, one work-item per image: the HOG part is scaled to unit L2 norm, an optional
 *    silhouette part (host-resized mask, values in [0, 1]) to norm `sil_weight`, and the
 *    concatenation divided by its norm. An all-zero part stays zero. Sums run in index order.
 */
#include "common.h"

/* MAX_BINS: from ucad_cl/abi.py (-D) */

typedef struct {
    int size;           /* S, crop side in pixels */
    int cell;           /* cell side in pixels, S % cell == 0 */
    int n_cells;        /* S / cell */
    int bins;           /* orientation bins, <= MAX_BINS */
    int is_signed;      /* 1: orientations over [0, 2 pi), 0: [0, pi) */
    int n_blocks;       /* n_cells - 1 */
    int d_hog;          /* n_blocks^2 * 4 * bins */
    int d_sil;          /* silhouette length, 0 when unused */
    float eps;          /* block normalisation epsilon */
    float clip;         /* L2-Hys clip value */
    float sil_weight;   /* norm of the silhouette part relative to the HOG part */
    float min_grad;     /* soft threshold on the gradient magnitude (units of 1/255 scale) */
} hog_params;

#define PI_F 3.14159265358979f

/* atan2(y, x) in [-pi, pi] from +, *, / and exact operations alone: atan on [0, 1] by Abramowitz
 * & Stegun 4.4.49 (|error| <= 2e-8 exactly; in float within 4e-7 rad, 2 ulp at pi: tests/test_features.py),
 * then the octant. The library atan2 may round differently on each device (OpenCL allows 6 ulp;
 * NVIDIA's and PoCL's differ), so the descriptor would too; this one gives the same bits on every
 * device with correctly rounded division (Runtime.build_source asks for it where supported). */
static inline float same_bits_atan2(float y, float x) {
    const float ax = fabs(x), ay = fabs(y);
    const float hi = fmax(ax, ay), lo = fmin(ax, ay);
    if (hi == 0.0f) return 0.0f;
    const float a = lo / hi, s = a * a;
    float q = 0.0028662257f;
    q = q * s - 0.0161657367f;
    q = q * s + 0.0429096138f;
    q = q * s - 0.0752896400f;
    q = q * s + 0.1065626393f;
    q = q * s - 0.1420889944f;
    q = q * s + 0.1999355085f;
    q = q * s - 0.3333314528f;
    float r = a * (1.0f + q * s);           /* atan(lo / hi) in [0, pi / 4] */
    if (ay > ax) r = 0.5f * PI_F - r;
    if (x < 0.0f) r = PI_F - r;
    return y < 0.0f ? -r : r;
}

static inline int px(global const uchar *im, int S, int y, int x, int c) {
    y = clamp(y, 0, S - 1);
    x = clamp(x, 0, S - 1);
    return (int)im[(y * S + x) * 3 + c];
}

kernel void hog_pixel_gradients(global const uchar *images, global float2 *grad, hog_params p) {
    const int pix = get_global_id(0);
    const int b = get_global_id(1);
    const int S = p.size;
    if (pix >= S * S) return;
    const int y = pix / S, x = pix % S;
    global const uchar *im = images + (size_t)b * S * S * 3;
    int gx = 0, gy = 0, best = 0;
    for (int c = 0; c < 3; ++c) {
        int dx = px(im, S, y, x + 1, c) - px(im, S, y, x - 1, c);
        int dy = px(im, S, y + 1, x, c) - px(im, S, y - 1, x, c);
        int m2 = dx * dx + dy * dy;
        if (m2 > best) { best = m2; gx = dx; gy = dy; }
    }
    float mag = sqrt((float)best) / 255.0f - p.min_grad;
    const float range = p.is_signed ? 2.0f * PI_F : PI_F;
    float t = same_bits_atan2((float)gy, (float)gx);
    if (t < 0.0f) t += 2.0f * PI_F;
    if (!p.is_signed && t >= PI_F) t -= PI_F;
    if (t >= range) t -= range;
    grad[(size_t)b * S * S + pix] = (float2)(best > 0 ? mag : 0.0f, t * ((float)p.bins / range) - 0.5f);
}

kernel void hog_cell_histograms(global const float2 *grad, global float *hist, hog_params p) {
    const int cell_id = get_global_id(0);
    const int b = get_global_id(1);
    if (cell_id >= p.n_cells * p.n_cells) return;
    const int cy = cell_id / p.n_cells, cx = cell_id % p.n_cells;
    const int S = p.size;
    global const float2 *g = grad + (size_t)b * S * S;
    float h[MAX_BINS];
    for (int k = 0; k < p.bins; ++k) h[k] = 0.0f;
    for (int y = cy * p.cell; y < (cy + 1) * p.cell; ++y) {
        for (int x = cx * p.cell; x < (cx + 1) * p.cell; ++x) {
            float2 mp = g[y * S + x];
            float mag = mp.x;
            if (mag <= 0.0f) continue;
            float fl = floor(mp.y);
            float frac = mp.y - fl;
            int b0 = (int)fl;
            int b1 = b0 + 1;
            if (b0 < 0) b0 += p.bins;
            if (b1 >= p.bins) b1 -= p.bins;
            h[b0] += mag * (1.0f - frac);
            h[b1] += mag * frac;
        }
    }
    global float *out = hist + ((size_t)b * p.n_cells * p.n_cells + cell_id) * p.bins;
    for (int k = 0; k < p.bins; ++k) out[k] = h[k];
}

kernel void hog_block_normalise(global const float *hist, global float *blocks, hog_params p) {
    const int block_id = get_global_id(0);
    const int b = get_global_id(1);
    if (block_id >= p.n_blocks * p.n_blocks) return;
    const int by = block_id / p.n_blocks, bx = block_id % p.n_blocks;
    const int nb = p.bins;
    global const float *h = hist + (size_t)b * p.n_cells * p.n_cells * nb;
    global float *out = blocks + (size_t)b * p.d_hog + (size_t)block_id * 4 * nb;
    float v[4 * MAX_BINS];
    float ss = 0.0f;
    for (int q = 0; q < 4; ++q) {
        int cell = (by + q / 2) * p.n_cells + (bx + q % 2);
        for (int k = 0; k < nb; ++k) {
            float x = h[cell * nb + k];
            v[q * nb + k] = x;
            ss += x * x;
        }
    }
    const float e2 = p.eps * p.eps;
    float inv = 1.0f / sqrt(ss + e2);
    float ss2 = 0.0f;
    for (int k = 0; k < 4 * nb; ++k) {
        float x = fmin(v[k] * inv, p.clip);
        v[k] = x;
        ss2 += x * x;
    }
    inv = 1.0f / sqrt(ss2 + e2);
    for (int k = 0; k < 4 * nb; ++k) out[k] = v[k] * inv;
}

kernel void hog_finalise(global const float *blocks, global const float *sil, global float *feats,
                         hog_params p, int n_images) {
    const int b = get_global_id(0);
    if (b >= n_images) return;
    global const float *x = blocks + (size_t)b * p.d_hog;
    global float *out = feats + (size_t)b * (p.d_hog + p.d_sil);
    float sh = 0.0f, ssil = 0.0f;
    for (int k = 0; k < p.d_hog; ++k) sh += x[k] * x[k];
    for (int k = 0; k < p.d_sil; ++k) ssil += sil[(size_t)b * p.d_sil + k] * sil[(size_t)b * p.d_sil + k];
    float nh = sqrt(sh), ns = sqrt(ssil);
    float wh = nh > 0.0f ? 1.0f : 0.0f;
    float ws = ns > 0.0f ? p.sil_weight : 0.0f;
    float total = sqrt(wh * wh + ws * ws);
    float ah = nh > 0.0f ? 1.0f / (nh * total) : 0.0f;
    float as = ns > 0.0f ? ws / (ns * total) : 0.0f;
    for (int k = 0; k < p.d_hog; ++k) out[k] = x[k] * ah;
    for (int k = 0; k < p.d_sil; ++k) out[p.d_hog + k] = sil[(size_t)b * p.d_sil + k] * as;
}
