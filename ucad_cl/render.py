"""Batched material-index rendering: all views of one mesh per launch (``kernels/raster.cl``).

``render_views(mesh, ring)`` returns per view a triangle-id map (uint32, 0xFFFFFFFF background),
a material-id map (uint16, material index + 1, 0 background) and linear camera-space depth
(float32, +inf background). One sample per pixel at its centre; no antialiasing, so ids never
blend. Visibility is decided by the 64-bit key (depth bits, face index) and atomic min: output is
bit-identical across runs, thread counts and work-group sizes. See raster.cl for the numerics.

Memory is bounded: views are rendered in chunks so that the per-pixel key buffer stays under
``max_key_bytes``; nothing is dropped when the list of large triangles fills (it grows, and the
pass is rerun).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .runtime import get_runtime
from .types import CameraRing, Mesh, ViewSet

PARAMS_DTYPE = np.dtype([("width", np.int32), ("height", np.int32), ("n_faces", np.int32),
                         ("n_views", np.int32), ("near", np.float32),
                         ("big_capacity", np.uint32)])
BUILD_OPTIONS = ("-cl-fp32-correctly-rounded-divide-sqrt",)
LOCAL_SMALL = (64, 1)   # work-group (faces, views); see bench/render.py and the README
LOCAL_PROJECT = (64, 1)  # work-group (vertices, views)
LANES = 16              # work-items sharing one large triangle (rows interleaved)
MAX_FACES = 2**32 - 2   # face ids must stay below the background id


@dataclass
class RenderStats:
    """Timings of the last render (seconds) and how many triangles took the large path."""

    upload: float = 0.0
    raster: float = 0.0
    resolve: float = 0.0
    big_triangles: int = 0
    reruns: int = 0
    chunks: int = 0
    extra: dict = field(default_factory=dict)


last_stats = RenderStats()


def render_views(mesh: Mesh, ring: CameraRing, *, max_key_bytes: int = 256 * 2**20,
                 local_size=LOCAL_SMALL) -> ViewSet:
    """Render material-index, triangle-id and depth maps of ``mesh`` for every camera of ``ring``."""
    return _render(mesh, ring, max_key_bytes=max_key_bytes, local_size=local_size)


def coverage_counts(mesh: Mesh, ring: CameraRing) -> np.ndarray:
    """(V, H, W) uint64: how many triangles cover each pixel centre (a test of the fill rule)."""
    return _render(mesh, ring, count=True)


def _render(mesh: Mesh, ring: CameraRing, *, max_key_bytes: int = 256 * 2**20,
            local_size=LOCAL_SMALL, count: bool = False):
    verts, faces, fmat = _validate(mesh)
    ls = (local_size, 1) if isinstance(local_size, int) else tuple(local_size)
    rt = get_runtime()
    import pyopencl as cl

    opts = BUILD_OPTIONS + (("-DUCAD_COUNT_COVERAGE",) if count else ())
    k_project = rt.kernel("raster", "project_vertices", opts)
    k_small = rt.kernel("raster", "raster_small", opts)
    k_big = rt.kernel("raster", "raster_big", opts)
    k_resolve = rt.kernel("raster", "resolve_maps", opts)
    V, H, W = ring.n_views, ring.height, ring.width
    npix = H * W
    stats = RenderStats()
    t0 = time.perf_counter()
    mf = cl.mem_flags
    ctx, q = rt.ctx, rt.queue
    d_verts = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=verts)
    d_faces = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=faces)
    d_fmat = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=fmat)
    P_all = projection_matrices(ring)

    n_verts = int(verts.shape[0])
    # views per launch: key buffer (8 B/pixel) and projected vertices (8 B/vertex) both bounded
    chunk = max(1, min(V, int(max_key_bytes // (8 * npix)), int(max_key_bytes // (8 * n_verts))))
    tri = np.empty((V, H, W), np.uint32)
    mat = np.empty((V, H, W), np.uint16)
    dep = np.empty((V, H, W), np.float32)
    counts = np.empty((V, H, W), np.uint64) if count else None
    # per-launch buffers are reused across calls (runtime scratch): no allocation and no page
    # faults on first touch for every mesh
    d_keys = rt.scratch("raster.keys", 8 * chunk * npix)
    d_tri = rt.scratch("raster.tri", 4 * chunk * npix)
    d_mat = rt.scratch("raster.mat", 2 * chunk * npix)
    d_dep = rt.scratch("raster.depth", 4 * chunk * npix)
    d_count = rt.scratch("raster.count", 4)
    d_pverts = rt.scratch("raster.pverts", 8 * chunk * n_verts)
    big_cap = 4096
    d_big = rt.scratch("raster.big", 8 * big_cap)
    big_cap = d_big.size // 8
    stats.upload = time.perf_counter() - t0

    for v0 in range(0, V, chunk):
        nv = min(chunk, V - v0)
        t1 = time.perf_counter()
        d_P = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=P_all[v0:v0 + nv].copy())
        cl.enqueue_fill_buffer(q, d_keys, np.uint64(0 if count else 0xFFFFFFFFFFFFFFFF), 0,
                               8 * nv * npix)
        prm = np.array([(W, H, faces.shape[0], nv, ring.near, big_cap)], PARAMS_DTYPE)
        cl.enqueue_nd_range_kernel(
            q, _args(k_project, d_verts, d_P, prm, np.uint32(n_verts), d_pverts),
            (_round_up(n_verts, LOCAL_PROJECT[0]), _round_up(nv, LOCAL_PROJECT[1])), LOCAL_PROJECT)
        while True:   # small triangles; large ones are listed (list grows and pass reruns)
            prm = np.array([(W, H, faces.shape[0], nv, ring.near, big_cap)], PARAMS_DTYPE)
            cl.enqueue_fill_buffer(q, d_count, np.uint32(0), 0, 4)
            cl.enqueue_nd_range_kernel(
                q, _args(k_small, d_verts, d_faces, d_P, d_pverts, np.uint32(n_verts), prm, d_keys,
                         d_big, d_count),
                (_round_up(faces.shape[0], ls[0]), _round_up(nv, ls[1])), ls)
            n_big_arr = np.zeros(1, np.uint32)
            cl.enqueue_copy(q, n_big_arr, d_count)
            n_big = int(n_big_arr[0])
            if n_big <= big_cap:
                break
            d_big = rt.scratch("raster.big", 8 * _round_up(n_big, 4096))
            big_cap = d_big.size // 8
            stats.reruns += 1
        if n_big:
            cl.enqueue_nd_range_kernel(
                q, _args(k_big, d_verts, d_faces, d_P, d_pverts, np.uint32(n_verts), prm, d_keys,
                         d_big, np.uint32(n_big)),
                (n_big, LANES), (1, LANES))
        stats.big_triangles += n_big
        q.finish()
        t2 = time.perf_counter()
        n = nv * npix
        if count:
            cl.enqueue_copy(q, counts[v0:v0 + nv], d_keys)
        else:
            cl.enqueue_nd_range_kernel(
                q, _args(k_resolve, d_keys, d_fmat, d_tri, d_mat, d_dep, np.uint32(n)),
                (_round_up(n, 256),), (256,))
            cl.enqueue_copy(q, tri[v0:v0 + nv], d_tri)
            cl.enqueue_copy(q, mat[v0:v0 + nv], d_mat)
            cl.enqueue_copy(q, dep[v0:v0 + nv], d_dep)
        q.finish()
        stats.raster += t2 - t1
        stats.resolve += time.perf_counter() - t2
        stats.chunks += 1
    global last_stats
    last_stats = stats
    if count:
        return counts
    return ViewSet(cameras=ring, tri_id=tri, mat_id=mat, depth=dep)


def projection_matrices(ring: CameraRing) -> np.ndarray:
    """(V, 12) float32 rows of K [R|t] per view, computed in float64."""
    P = np.einsum("ij,vjk->vik", ring.K, ring.w2c[:, :3, :])
    return np.ascontiguousarray(P.reshape(ring.n_views, 12), dtype=np.float32)


def _validate(mesh: Mesh):
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    fm = np.asarray(mesh.face_material)
    where = f"mesh {mesh.path!r}"
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{where}: vertices must be (N, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"{where}: faces must be (F, 3), got {f.shape}")
    if fm.shape != (f.shape[0],):
        raise ValueError(f"{where}: face_material must be ({f.shape[0]},), got {fm.shape}")
    if f.shape[0] > MAX_FACES:
        raise ValueError(f"{where}: {f.shape[0]} faces exceed the id range")
    if f.shape[0] == 0:
        raise ValueError(f"{where}: the mesh has no faces; there is nothing to render")
    if not np.all(np.isfinite(v)):
        bad = int(np.count_nonzero(~np.isfinite(v).all(axis=1)))
        raise ValueError(f"{where}: {bad} vertices are NaN or infinite; ingest rejects such meshes")
    if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
        raise ValueError(f"{where}: face indices out of range 0..{v.shape[0] - 1}")
    if fm.size and int(fm.max()) >= 0xFFFF:
        raise ValueError(f"{where}: material index {int(fm.max())} does not fit a uint16 id")
    return (np.ascontiguousarray(v, np.float32), np.ascontiguousarray(f, np.uint32),
            np.ascontiguousarray(fm, np.uint16))


def _args(kernel, *args):
    kernel.set_args(*args)
    return kernel


def _round_up(n: int, m: int) -> int:
    return ((n + m - 1) // m) * m
