"""Batched material-index rendering: all views of one mesh per launch (``kernels/raster_*.cl``).

``render_views(mesh, ring)`` returns per view a triangle-id map (uint32, 0xFFFFFFFF background),
a material-id map (uint16, material index + 1, 0 background) and linear camera-space depth
(float32, +inf background). One sample per pixel at its centre; no antialiasing, so ids never
blend. Visibility is decided by the minimum 64-bit key (depth bits, face index): output is
bit-identical across runs, thread counts and work-group sizes. See kernels/raster_common.h for
the numerics.

Two kernel paths give the same bytes: ``parallel`` (one work-item per face and view, atomic min;
for GPUs) and ``serial`` (one work-item per view, faces 16 at a time in explicit vectors, no
atomics; for CPUs: on PoCL it measured 2x the parallel path at 100k triangles, 256 px).
``path="auto"`` picks by device type; the environment variable ``UCAD_RASTER_PATH`` overrides it.

Memory is bounded: views are rendered in chunks so that the per-pixel key buffer and the projected
vertices stay under ``max_key_bytes``. Nothing is dropped: on the parallel path, when the list of
large triangles fills it grows and the pass is rerun; the serial path draws large triangles inline.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from .abi import RASTER_PARAMS
from .runtime import Runtime, aligned_empty, get_runtime
from .artifacts import CameraRing, Mesh, ViewSet

LOCAL_SMALL = (64, 1)   # work-group (faces, views); see bench/render.py and docs/OPENCL.md
LOCAL_PROJECT = (64, 1)  # work-group (vertices, views)
LANES = 16              # work-items sharing one large triangle (rows interleaved)
MAX_FACES = 2**32 - 2   # face ids must stay below the background id


@dataclass
class RenderStats:
    """Timings of one render (seconds) and how many triangles took the large path; pass one
    as ``render_views(..., stats=)`` to have it filled."""

    upload: float = 0.0
    raster: float = 0.0
    resolve: float = 0.0
    big_triangles: int = 0
    reruns: int = 0
    chunks: int = 0
    extra: dict = field(default_factory=dict)


def render_views(mesh: Mesh, ring: CameraRing, *, runtime: Runtime | None = None,
                 max_key_bytes: int = 256 * 2**20, local_size=LOCAL_SMALL, path: str = "auto",
                 stats: RenderStats | None = None) -> ViewSet:
    """Render material-index, triangle-id and depth maps of ``mesh`` for every camera of ``ring``
    on ``runtime`` (default: the process's, ``get_runtime()``).

    ``path``: "auto", "serial" or "parallel" (see the module docstring); ``local_size`` applies
    to the parallel path's first pass; ``stats``, when given, receives timings and counts."""
    return _render(mesh, ring, runtime or get_runtime(), max_key_bytes=max_key_bytes,
                   local_size=local_size, path=path, stats=stats)


def raster_path(path: str = "auto", runtime: Runtime | None = None) -> str:
    """The kernel path ``render_views`` will use on ``runtime``: "serial" or "parallel"."""
    path = os.environ.get("UCAD_RASTER_PATH", "") or path
    if path == "auto":
        import pyopencl as cl

        rt = runtime or get_runtime()
        return "serial" if rt.device.type & cl.device_type.CPU else "parallel"
    if path not in ("serial", "parallel"):
        raise ValueError(f"unknown raster path {path!r}: use 'auto', 'serial' or 'parallel' "
                         "(argument or UCAD_RASTER_PATH)")
    return path


def coverage_counts(mesh: Mesh, ring: CameraRing, *, runtime: Runtime | None = None,
                    path: str = "auto") -> np.ndarray:
    """(V, H, W) uint64: how many triangles cover each pixel centre (a test of the fill rule)."""
    return _render(mesh, ring, runtime or get_runtime(), count=True, path=path)


def _render(mesh: Mesh, ring: CameraRing, rt: Runtime, *, max_key_bytes: int = 256 * 2**20,
            local_size=LOCAL_SMALL, count: bool = False, path: str = "auto",
            stats: RenderStats | None = None):
    verts, faces, fmat = _validate(mesh)
    # the serial kernel gathers with signed 32-bit offsets (2 per vertex)
    serial = raster_path(path, rt) == "serial" and 2 * verts.shape[0] < 2**31
    import pyopencl as cl

    opts = ("-DUCAD_COUNT_COVERAGE",) if count else ()
    program = "raster_serial" if serial else "raster_parallel"
    V, H, W = ring.n_views, ring.height, ring.width
    npix = H * W
    stats = RenderStats() if stats is None else stats
    t0 = time.perf_counter()
    mf = cl.mem_flags
    ctx, q = rt.ctx, rt.queue
    d_verts = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=verts)
    d_faces = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=faces)
    d_fmat = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=fmat)
    P_all = projection_matrices(ring)
    n_verts = int(verts.shape[0])
    # views per launch: key buffer (8 B/pixel) and projected vertices (8 B/vertex, + 4 B of depth
    # on the serial path) both bounded
    per_vert = 12 if serial else 8
    chunk = max(1, min(V, int(max_key_bytes // (8 * npix)),
                       int(max_key_bytes // (per_vert * n_verts))))
    if count:
        outs = (np.empty((V, H, W), np.uint64),)
    else:   # page-aligned, so that the serial path can write them in place
        outs = (aligned_empty((V, H, W), np.uint32), aligned_empty((V, H, W), np.uint16),
                aligned_empty((V, H, W), np.float32))
    # per-launch buffers are reused across calls (runtime scratch): no allocation and no page
    # faults on first touch for every mesh
    d_keys = rt.scratch("raster.keys", 8 * chunk * npix)
    d_pverts = rt.scratch("raster.pverts", 8 * chunk * n_verts)
    # depths are stored for the serial path only (store_depth = 0 leaves the stand-in unwritten)
    d_pdepth = rt.scratch("raster.pdepth", 4 * chunk * n_verts) if serial else d_pverts
    if serial:   # one index array per corner, for 16-lane gathers
        corners = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(c))
                   for c in faces.T]
    stats.upload += time.perf_counter() - t0

    # the serial path projects 16 vertices a work-item in vector code (raster_serial.cl)
    k_project = rt.kernel(program, "project_vertices16" if serial else "project_vertices", opts)
    per_item = 16 if serial else 1
    for v0 in range(0, V, chunk):
        nv = min(chunk, V - v0)
        t1 = time.perf_counter()
        d_P = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=P_all[v0:v0 + nv].copy())
        prm = np.array([(W, H, faces.shape[0], nv, ring.near, 0)], RASTER_PARAMS)
        args = (d_verts, d_P, prm, np.uint32(n_verts), d_pverts, d_pdepth) + (
            () if serial else (np.uint32(0),))
        cl.enqueue_nd_range_kernel(
            q, _args(k_project, *args),
            (_round_up(-(-n_verts // per_item), LOCAL_PROJECT[0]),
             _round_up(nv, LOCAL_PROJECT[1])), LOCAL_PROJECT)
        bufs = (d_verts, d_faces, d_P, d_pverts, d_keys, d_fmat)
        chunk_outs = [o[v0:v0 + nv] for o in outs]
        if serial:
            t2 = _draw_serial(rt, opts, bufs, corners, d_pdepth, n_verts, prm, chunk_outs, count)
        else:
            t2 = _draw_parallel(rt, opts, bufs, n_verts, prm, local_size, chunk_outs, count, stats)
        stats.raster += t2 - t1
        stats.resolve += time.perf_counter() - t2
        stats.chunks += 1
    return outs[0] if count else ViewSet(cameras=ring, tri_id=outs[0], mat_id=outs[1],
                                         depth=outs[2])


def _draw_serial(rt, opts, bufs, corners, d_pdepth, n_verts, prm, outs, count) -> float:
    """One chunk on the serial path: one launch clears, draws and resolves every view, writing
    the maps in place (USE_HOST_PTR on the aligned outputs: no copy back). Returns the time the
    kernel finished."""
    import pyopencl as cl

    d_verts, d_faces, d_P, d_pverts, d_keys, d_fmat = bufs
    ctx, q = rt.ctx, rt.queue
    nv = int(prm["n_views"][0])
    if count:
        d_outs = (d_keys,) * 3   # not written
    else:
        d_outs = [cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=o)
                  for o in outs]
    k = rt.kernel("raster_serial", "raster_views_serial", opts)
    cl.enqueue_nd_range_kernel(
        q, _args(k, d_verts, d_faces, *corners, d_P, d_pverts, d_pdepth, np.uint32(n_verts), prm,
                 d_keys, d_fmat, *d_outs), (nv,), (1,))
    q.finish()
    t2 = time.perf_counter()
    if count:
        cl.enqueue_copy(q, outs[0], d_keys)
        q.finish()
        return t2
    for buf in d_outs:   # a map makes the host memory current on any device (free on PoCL)
        view, _ = cl.enqueue_map_buffer(q, buf, cl.map_flags.READ, 0, (buf.size,), np.uint8)
        view.base.release(q)
        buf.release()
    return t2


def _draw_parallel(rt, opts, bufs, n_verts, prm, local_size, outs, count, stats) -> float:
    """One chunk on the parallel path: small triangles per (face, view), large ones listed and
    spread over LANES work-items (the list grows and the pass reruns when it overflows), then
    resolve and copy back. Returns the time drawing finished."""
    import pyopencl as cl

    d_verts, d_faces, d_P, d_pverts, d_keys, d_fmat = bufs
    q = rt.queue
    ls = (local_size, 1) if isinstance(local_size, int) else tuple(local_size)
    n_faces, nv = int(prm["n_faces"][0]), int(prm["n_views"][0])
    n = nv * int(prm["width"][0]) * int(prm["height"][0])
    d_count = rt.scratch("raster.count", 4)
    d_big = rt.scratch("raster.big", 8 * 4096)
    k_small = rt.kernel("raster_parallel", "raster_small", opts)
    cl.enqueue_fill_buffer(q, d_keys, np.uint64(0 if count else 0xFFFFFFFFFFFFFFFF), 0, 8 * n)
    while True:
        prm["big_capacity"] = d_big.size // 8
        cl.enqueue_fill_buffer(q, d_count, np.uint32(0), 0, 4)
        cl.enqueue_nd_range_kernel(
            q, _args(k_small, d_verts, d_faces, d_P, d_pverts, np.uint32(n_verts), prm, d_keys,
                     d_big, d_count),
            (_round_up(n_faces, ls[0]), _round_up(nv, ls[1])), ls)
        n_big_arr = np.zeros(1, np.uint32)
        cl.enqueue_copy(q, n_big_arr, d_count)
        n_big = int(n_big_arr[0])
        if n_big <= d_big.size // 8:
            break
        d_big = rt.scratch("raster.big", 8 * _round_up(n_big, 4096))
        stats.reruns += 1
    if n_big:
        cl.enqueue_nd_range_kernel(
            q, _args(rt.kernel("raster_parallel", "raster_big", opts), d_verts, d_faces, d_P, d_pverts,
                     np.uint32(n_verts), prm, d_keys, d_big, np.uint32(n_big)),
            (n_big, LANES), (1, LANES))
    stats.big_triangles += n_big
    q.finish()
    t2 = time.perf_counter()
    if count:
        cl.enqueue_copy(q, outs[0], d_keys)
    else:
        d_outs = [rt.scratch(f"raster.out{i}", o.nbytes) for i, o in enumerate(outs)]
        cl.enqueue_nd_range_kernel(
            q, _args(rt.kernel("raster_parallel", "resolve_maps", opts), d_keys, d_fmat, *d_outs,
                     np.uint32(n)), (_round_up(n, 256),), (256,))
        for o, d in zip(outs, d_outs):
            cl.enqueue_copy(q, o, d)
    q.finish()
    return t2


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
