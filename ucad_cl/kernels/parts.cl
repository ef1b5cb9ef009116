/* Joint (material id, part) histograms of rendered views: the one pass behind IoU part
 * classification (ucad_cl/classify.py).
 *
 * Input per view v (n_pixels = H*W pixels, row-major):
 *   mat_id[v][i]    uint16 material id (0 = background)
 *   part_bits[v][i] uint16, bit p set when pixel i is inside the mask of part p (p < 16)
 * Output per view, a zero-initialised table hist[v][id][c] of uint32 with row = 1 + n_parts:
 *   c = 0        : |material id| (visible pixels of that id; id 0 = background)
 *   c = 1 + p    : |material id ∩ part p|
 * so |part p| is the column sum over all ids (background row included).
 *
 * Each work-item scans a contiguous run of pixels_per_item pixels of one view, run-length
 * compresses equal (id, bits) pixels in private memory and adds whole runs to the work-group's
 * local table with atomics; the group then adds its local table to the global one with atomics.
 * Counts are integers, so the result does not depend on scheduling: bit-identical every run.
 * Grid: dimension 0 = work-items over the pixels of a view, dimension 1 = view.
 */
#include "common.h"

typedef struct {
    uint n_pixels;          /* H * W of every view */
    uint n_views;
    uint n_ids;             /* material ids 0 .. n_ids-1 (host: max id + 1) */
    uint n_parts;           /* 1 .. 16 */
    uint pixels_per_item;   /* contiguous pixels scanned by one work-item */
    uint pad;
} part_hist_params;

#define PART_HIST_BODY(SPACE, TABLE)                                                        \
    const uint row = 1u + prm.n_parts;                                                      \
    const uint start = (uint)get_global_id(0) * prm.pixels_per_item;                        \
    const uint end = min(start + prm.pixels_per_item, prm.n_pixels);                        \
    const size_t base = (size_t)get_global_id(1) * prm.n_pixels;                            \
    uint run_id = 0u, run_bits = 0u, run_n = 0u;                                            \
    for (uint i = start; i < end; ++i) {                                                    \
        const uint id = mat_id[base + i];                                                   \
        const uint bits = part_bits[base + i];                                              \
        if (id == run_id && bits == run_bits) { ++run_n; continue; }                        \
        if (run_n) {                                                                        \
            SPACE uint *r = TABLE + run_id * row;                                           \
            atomic_add(r, run_n);                                                           \
            for (uint b = run_bits, p = 0u; b; b >>= 1, ++p)                                \
                if (b & 1u) atomic_add(r + 1u + p, run_n);                                  \
        }                                                                                   \
        run_id = id; run_bits = bits; run_n = 1u;                                           \
    }                                                                                       \
    if (run_n) {                                                                            \
        SPACE uint *r = TABLE + run_id * row;                                               \
        atomic_add(r, run_n);                                                               \
        for (uint b = run_bits, p = 0u; b; b >>= 1, ++p)                                    \
            if (b & 1u) atomic_add(r + 1u + p, run_n);                                      \
    }

/* Work-group-local table (n_ids * (1 + n_parts) uints of local memory), merged at the end. */
__kernel void material_part_histogram(__global const ushort *mat_id,
                                      __global const ushort *part_bits,
                                      const part_hist_params prm,
                                      __global uint *hist,
                                      __local uint *lhist)
{
    const uint n_loc = prm.n_ids * (1u + prm.n_parts);
    const uint lid = (uint)get_local_id(0), lsz = (uint)get_local_size(0);
    for (uint k = lid; k < n_loc; k += lsz) lhist[k] = 0u;
    barrier(CLK_LOCAL_MEM_FENCE);
    {
        PART_HIST_BODY(__local, lhist)
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    __global uint *out = hist + (size_t)get_global_id(1) * n_loc;
    for (uint k = lid; k < n_loc; k += lsz) {
        const uint c = lhist[k];
        if (c) atomic_add(out + k, c);
    }
}

/* Same table without local memory (for material counts whose table does not fit). */
__kernel void material_part_histogram_global(__global const ushort *mat_id,
                                             __global const ushort *part_bits,
                                             const part_hist_params prm,
                                             __global uint *hist)
{
    __global uint *out = hist + (size_t)get_global_id(1) * prm.n_ids * (1u + prm.n_parts);
    PART_HIST_BODY(__global, out)
}
