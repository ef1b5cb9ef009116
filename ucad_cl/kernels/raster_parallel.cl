/* raster_parallel.cl: the parallel raster path (GPUs); one program with raster_common.h.
 *
 * raster_small: one work-item per (face, view). A triangle whose clipped bounding box exceeds
 * BIG_PIXELS pixels is appended to a list instead, and raster_big spreads each listed triangle
 * over LANES work-items (rows interleaved). If the list overflows, the host enlarges it and
 * reruns raster_small: atomic_min is idempotent, so a rerun only repeats work. resolve_maps then
 * turns the keys into maps. Output is raster_serial.cl's, bit for bit.
 */
#include "raster_common.h"

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

/* Keys -> triangle id, material id (= face material + 1, 0 background), depth (+inf background). */
kernel void resolve_maps(global const ulong *keys, global const ushort *face_material,
                         global uint *tri_id, global ushort *mat_id, global float *depth, uint n) {
    uint g = get_global_id(0);
    if (g >= n) return;
    resolve_key(keys[g], face_material, g, tri_id, mat_id, depth);
}
