/* shade.cl: flat Lambert + Blinn-Phong shading of rendered triangle-id maps (see ucad_cl/shade.py
 * for the model, units and conventions; this kernel is its device path, the NumPy code there is
 * the reference it is tested against, to within one 8-bit level).
 *
 * shade_pixels: one work-item per pixel of the (V, H, W) batch. Per view: R (3x3, row-major)
 * and t of the world-to-camera matrix. Per face: unit normal and first vertex (canonical
 * frame), material. Per pixel position: its half vector, from half_vectors (run first).
 */
#include "common.h"

typedef struct {
    float kinv[9];          /* K^-1, row-major */
    float light[3];         /* unit vector toward the light, camera frame */
    float ambient, specular, shininess;
    int width, height, n_views;
    int int_shininess;      /* shininess when it is an integer in [1, 1024], else 0 */
    uchar bg[3], pad;       /* background colour (sRGB 8-bit) */
} shade_params;

/* Linear value -> sRGB 8-bit level, exactly: the number of the 255 level thresholds (computed in
 * float64 on the host: level k starts where floor(srgb(x) * 255 + 0.5) becomes k) that are <= x.
 * A table of SRGB_BUCKETS entries gives a level that is never above the answer for the bucket
 * of x (the host builds it one bucket low, so float rounding of the bucket index cannot
 * overshoot), then at most a few comparisons step up to it: cheaper on PoCL than a binary
 * search or pow(). 65,536 buckets (64 KiB) against 4,096: the start is the answer or one below
 * it far more often, 144 views of a 50k-triangle mesh shade in ~40 ms against ~45. */
/* SRGB_BUCKETS: from ucad_cl/abi.py (-D) */
static inline uchar srgb8(global const float *thr, global const uchar *start, float x) {
    float c = fmin(fmax(x, 0.0f), 1.0f);                   /* NaN -> 0 (fmax returns 0) */
    int lvl = start[(int)(c * (float)(SRGB_BUCKETS - 1))];
    while (lvl < 255 && x >= thr[lvl]) ++lvl;
    return (uchar)lvl;
}

/* The Blinn-Phong half vector of every pixel p of a view (the same for every view, since the
 * light moves with the camera): h = normalize(l + v), v = -K^-1 (j + 0.5, i + 0.5, 1)
 * normalised, the unit vector from the surface to the camera (j the column, i the row). One
 * work-item per pixel, computed once per call instead of once per pixel of every view (its two
 * correctly rounded square roots and divisions were half of shade_pixels' time on PoCL). */
kernel void half_vectors(shade_params prm, global float *half_vec /* W x H x 3 */) {
    uint p = get_global_id(0);
    if (p >= (uint)(prm.width * prm.height)) return;
    float3 l = (float3)(prm.light[0], prm.light[1], prm.light[2]);
    float j = (float)(p % (uint)prm.width) + 0.5f, i = (float)(p / (uint)prm.width) + 0.5f;
    float3 r = (float3)(prm.kinv[0] * j + prm.kinv[1] * i + prm.kinv[2],
                        prm.kinv[3] * j + prm.kinv[4] * i + prm.kinv[5],
                        prm.kinv[6] * j + prm.kinv[7] * i + prm.kinv[8]);
    float3 h = l - r / sqrt(r.x * r.x + r.y * r.y + r.z * r.z);
    h = h / sqrt(h.x * h.x + h.y * h.y + h.z * h.z);
    vstore3(h, p, half_vec);
}

kernel void shade_pixels(global const uint *tri_id, global const float *w2c /* V x 12 */,
                         global const float *normals /* F x 3 */, global const float *v0 /* F x 3 */,
                         global const ushort *face_material, global const float *albedo /* M x 3 */,
                         global const float *thresholds /* 255 */,
                         global const uchar *bucket_start /* SRGB_BUCKETS */,
                         global const float *half_vec /* W x H x 3 */, shade_params prm,
                         global uchar *rgb) {
    uint g = get_global_id(0);
    uint npix = (uint)(prm.width * prm.height);
    if (g >= npix * (uint)prm.n_views) return;
    uint view = g / npix, p = g - view * npix;
    uint t = tri_id[g];
    global uchar *o = rgb + 3 * (size_t)g;
    if (t == UCAD_BG_TRI) { o[0] = prm.bg[0]; o[1] = prm.bg[1]; o[2] = prm.bg[2]; return; }
    global const float *M = w2c + 12 * view;
    float3 n = (float3)(normals[3 * t], normals[3 * t + 1], normals[3 * t + 2]);
    float3 a = (float3)(v0[3 * t], v0[3 * t + 1], v0[3 * t + 2]);
    float3 nc = (float3)(M[0] * n.x + M[1] * n.y + M[2] * n.z,
                         M[4] * n.x + M[5] * n.y + M[6] * n.z,
                         M[8] * n.x + M[9] * n.y + M[10] * n.z);
    float3 pc = (float3)(M[0] * a.x + M[1] * a.y + M[2] * a.z + M[3],
                         M[4] * a.x + M[5] * a.y + M[6] * a.z + M[7],
                         M[8] * a.x + M[9] * a.y + M[10] * a.z + M[11]);
    if (nc.x * pc.x + nc.y * pc.y + nc.z * pc.z > 0.0f) nc = -nc;     /* face the camera */
    float3 l = (float3)(prm.light[0], prm.light[1], prm.light[2]);
    float diffuse = fmax(nc.x * l.x + nc.y * l.y + nc.z * l.z, 0.0f);
    float3 h = vload3(p, half_vec);     /* the pixel's Blinn-Phong half vector (half_vectors) */
    int degenerate = n.x == 0.0f && n.y == 0.0f && n.z == 0.0f;
    float nh = fmax(nc.x * h.x + nc.y * h.y + nc.z * h.z, 0.0f);
    /* nh^shininess: by repeated squaring for an integer exponent (the usual case; exp2/log2
     * are scalar library calls on PoCL and cost more than the rest of the kernel), else as
     * exp2(shininess * log2(nh)); nh = 0 gives 0 */
    float spec = 0.0f;
    if (!degenerate && nh > 0.0f) {
        if (prm.int_shininess > 0) {
            float r = 1.0f, b = nh;
            for (int e = prm.int_shininess; e > 0; e >>= 1) {
                if (e & 1) r *= b;
                b *= b;
            }
            spec = prm.specular * r;
        } else {
            spec = prm.specular * exp2(prm.shininess * log2(nh));
        }
    }
    uint m = face_material[t];
    float k = prm.ambient + (1.0f - prm.ambient) * diffuse;
    for (int c = 0; c < 3; ++c)
        o[c] = srgb8(thresholds, bucket_start, albedo[3 * m + c] * k + spec);
}

/* shade_pixels for CPU devices: 16 consecutive pixels of one view per work-item, in explicit
 * 16-lane vectors (PoCL leaves shade_pixels scalar; a branch-free scalar kernel it could
 * vectorize measured 8.5x slower, because 81 % of the pixels are background: here a group of 16
 * background pixels is written at once). The same expressions in the same order (no contraction,
 * the same repeated squaring, the same threshold steps), so the same bytes; for an integer
 * shininess only (the host uses shade_pixels otherwise) and views of a multiple of 16 pixels.
 * Gathers: GATHER16 (common.h). */

static inline uint16 srgb8_16(global const float *thr, global const uchar *start, float16 x) {
    float16 c = fmin(fmax(x, 0.0f), 1.0f);
    int16 bucket = convert_int16(c * (float)(SRGB_BUCKETS - 1));
    int16 lvl = convert_int16(GATHER16(uint16, start, bucket));
    for (;;) {
        int16 below = lvl < 255;
        int16 idx = below ? lvl : (int16)0;
        int16 up = below & (x >= GATHER16(float16, thr, idx));
        if (!any(up)) break;
        lvl -= up;   /* up is -1 where the level steps */
    }
    return convert_uint16(lvl);
}

kernel void shade_pixels16(global const uint *tri_id, global const float *w2c /* V x 12 */,
                           global const float *normals /* F x 3 */,
                           global const float *v0 /* F x 3 */,
                           global const ushort *face_material,
                           global const float *albedo /* M x 3 */,
                           global const float *thresholds /* 255 */,
                           global const uchar *bucket_start /* SRGB_BUCKETS */,
                           global const float *half_vec /* W x H x 3 */, shade_params prm,
                           global uchar *rgb) {
    uint g0 = get_global_id(0) * 16;
    uint npix = (uint)(prm.width * prm.height);
    if (g0 >= npix * (uint)prm.n_views) return;
    uint view = g0 / npix, p0 = g0 - view * npix;
    uint16 t = vload16(0, tri_id + g0);
    int16 bg = t == (uint16)UCAD_BG_TRI;
    global uchar *o = rgb + 3 * (size_t)g0;
    if (all(bg)) {
        for (int q = 0; q < 16; ++q) { o[3 * q] = prm.bg[0]; o[3 * q + 1] = prm.bg[1]; o[3 * q + 2] = prm.bg[2]; }
        return;
    }
    uint16 f = bg ? (uint16)0 : t;
    uint16 f3 = 3 * f;
    float16 nx = GATHER16(float16, normals, f3), ny = GATHER16(float16, normals, f3 + 1);
    float16 nz = GATHER16(float16, normals, f3 + 2);
    float16 ax = GATHER16(float16, v0, f3), ay = GATHER16(float16, v0, f3 + 1);
    float16 az = GATHER16(float16, v0, f3 + 2);
    global const float *M = w2c + 12 * view;
    float16 ncx = M[0] * nx + M[1] * ny + M[2] * nz;
    float16 ncy = M[4] * nx + M[5] * ny + M[6] * nz;
    float16 ncz = M[8] * nx + M[9] * ny + M[10] * nz;
    float16 pcx = M[0] * ax + M[1] * ay + M[2] * az + M[3];
    float16 pcy = M[4] * ax + M[5] * ay + M[6] * az + M[7];
    float16 pcz = M[8] * ax + M[9] * ay + M[10] * az + M[11];
    int16 flip = ncx * pcx + ncy * pcy + ncz * pcz > 0.0f;        /* face the camera */
    ncx = flip ? -ncx : ncx; ncy = flip ? -ncy : ncy; ncz = flip ? -ncz : ncz;
    float16 diffuse = fmax(ncx * prm.light[0] + ncy * prm.light[1] + ncz * prm.light[2], 0.0f);
    uint16 h3 = 3 * (p0 + (uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
    float16 hx = GATHER16(float16, half_vec, h3), hy = GATHER16(float16, half_vec, h3 + 1);
    float16 hz = GATHER16(float16, half_vec, h3 + 2);
    int16 degenerate = (nx == 0.0f) & (ny == 0.0f) & (nz == 0.0f);
    float16 nh = fmax(ncx * hx + ncy * hy + ncz * hz, 0.0f);
    float16 r = 1.0f, b = nh;
    for (int e = prm.int_shininess; e > 0; e >>= 1) {
        if (e & 1) r *= b;
        b *= b;
    }
    float16 spec = (~degenerate & (nh > 0.0f)) ? prm.specular * r : (float16)0.0f;
    uint16 m3 = 3 * convert_uint16(GATHER16(ushort16, face_material, f));
    float16 k = prm.ambient + (1.0f - prm.ambient) * diffuse;
    uint16 c0 = srgb8_16(thresholds, bucket_start, GATHER16(float16, albedo, m3) * k + spec);
    uint16 c1 = srgb8_16(thresholds, bucket_start, GATHER16(float16, albedo, m3 + 1) * k + spec);
    uint16 c2 = srgb8_16(thresholds, bucket_start, GATHER16(float16, albedo, m3 + 2) * k + spec);
    c0 = bg ? (uint16)prm.bg[0] : c0; c1 = bg ? (uint16)prm.bg[1] : c1;
    c2 = bg ? (uint16)prm.bg[2] : c2;
    uint cc[3][16];
    vstore16(c0, 0, cc[0]); vstore16(c1, 0, cc[1]); vstore16(c2, 0, cc[2]);
    for (int q = 0; q < 16; ++q) {
        o[3 * q] = (uchar)cc[0][q]; o[3 * q + 1] = (uchar)cc[1][q]; o[3 * q + 2] = (uchar)cc[2][q];
    }
}
