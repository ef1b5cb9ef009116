"""Device self-test: does one OpenCL device run this project's kernels, and correctly?

``check_device(spec)`` opens exactly the device ``spec`` ("P:D"), then runs ``CHECKS`` in order
and returns the seconds it took, or raises :class:`SelfTestFailed` with the first failure as one
line. It is meant to run in a child process (``ucad_cl.runtime.device_status`` calls it through
``system.call_isolated`` and caches the verdict on disk per device, driver and kernel sources):
a broken OpenCL compiler may abort the process that uses it (PyPI's PoCL 3.0 on an AMD Zen 4
builds our programs, then cannot create their kernels, and LLVM aborts the interpreter at exit),
and the caller must survive that.

The checks, each against an independent reference computed here:

* ``kernels``: every program of ``ucad_cl/kernels`` builds with the kernel ABI's constants and
  every kernel it declares can be created (``clCreateKernel``: where the Zen 4 build fails with
  INVALID_KERNEL_NAME);
* ``render``: a small scene of overlapping, tilted triangles in two views through both raster
  paths, against a NumPy ray cast through the pixel centres (triangle ids on all but 1 % of the
  pixels, MAX_EDGE_PIXELS: centres on a shared edge may go either way; depth: median relative
  error 1e-4, largest 1e-2: the kernels interpolate depth in fixed point);
* ``canny``: two noise images against OpenCV's ``cv2.Canny`` (bit-identical, as the kernel is);
* ``search``: a 16 x 200 exact k-nearest search against NumPy distances.

``checks`` selects others: "module:function" names of functions ``f(runtime)`` that raise
``SelfTestFailed`` (tests/test_selftest.py feeds it a program whose kernels cannot be created
and a kernel that returns wrong results).
"""
from __future__ import annotations

import importlib
import re
import time
from importlib import resources
from typing import Sequence

import numpy as np

from .artifacts import Material, Mesh
from .cameras import make_ring
from .edges import canny
from .render import render_views
from .runtime import Runtime, create_unchecked_runtime, kernel_source
from .search import FeatureIndex

CHECKS: tuple[str, ...] = ("ucad_cl.selftest:check_kernels", "ucad_cl.selftest:check_render",
                           "ucad_cl.selftest:check_canny", "ucad_cl.selftest:check_search")
MAX_EDGE_PIXELS = 0.01          # render: share of pixels whose triangle id may differ
TIMEOUT_S = 900.0               # a first build of every program on a slow PoCL takes ~1 min


class SelfTestFailed(RuntimeError):
    """A check failed; the message is one line naming the check and what went wrong."""


def check_device(spec: str, checks: Sequence[str] = CHECKS) -> float:
    """Run ``checks`` on the device ``spec`` ("P:D"); seconds taken, or SelfTestFailed."""
    t0 = time.perf_counter()
    rt = create_unchecked_runtime(spec)
    for name in checks:
        module, func = name.split(":")
        check = getattr(importlib.import_module(module), func)
        try:
            check(rt)
        except SelfTestFailed:
            raise
        except Exception as exc:  # noqa: BLE001 - any error of the device is the verdict
            first = (str(exc).strip().splitlines() or [""])[0]
            raise SelfTestFailed(f"{func}: {type(exc).__name__}: {first}") from None
    rt.queue.finish()
    return time.perf_counter() - t0


def check_kernels(rt: Runtime) -> None:
    """Every program of ``ucad_cl/kernels`` builds and every kernel it declares can be
    created."""
    files = sorted(p.name[:-3] for p in resources.files("ucad_cl.kernels").iterdir()
                   if p.name.endswith(".cl"))
    for name in files:
        check_program(rt, f"{name}.cl", kernel_source(name))


def check_program(rt: Runtime, label: str, source: str) -> None:
    """``source`` builds (``Runtime.build_source``) and every kernel it declares
    (``kernel_names``) can be created; SelfTestFailed naming ``label`` otherwise."""
    import pyopencl as cl

    try:
        prg = rt.build_source(source)
    except cl.Error as exc:
        first = (str(exc).strip().splitlines() or [""])[0]
        raise SelfTestFailed(f"kernels: {label} does not build ({first})") from None
    for kernel in kernel_names(source):
        try:
            cl.Kernel(prg, kernel)
        except cl.Error as exc:
            raise SelfTestFailed(f"kernels: {label} builds but kernel {kernel!r} cannot be "
                                 f"created ({getattr(exc, 'code', exc)})") from None


def kernel_names(source: str) -> list[str]:
    """Names of the kernels an OpenCL C source declares (``kernel void NAME(`` or
    ``__kernel void NAME(``, attributes allowed between), in order."""
    pat = r"\b_?_?kernel\s+(?:__attribute__\s*\(\(.*?\)\)\s*)*void\s+(\w+)\s*\("
    return re.findall(pat, source, flags=re.S)


def check_render(rt: Runtime) -> None:
    """Both raster paths against a NumPy ray cast of a small scene."""
    mesh = _scene()
    ring = make_ring(azimuths=[25.0, 205.0], elevations=[20.0], size=(40, 30))
    ref_tri, ref_depth = _ray_cast(mesh, ring.K, ring.w2c, ring.width, ring.height)
    for path in ("serial", "parallel"):
        views = render_views(mesh, ring, runtime=rt, path=path)
        tri = views.tri_id.astype(np.int64)
        tri[views.tri_id == 0xFFFFFFFF] = -1
        differ = np.count_nonzero(tri != ref_tri)
        if differ > MAX_EDGE_PIXELS * tri.size:
            raise SelfTestFailed(f"render ({path} path): {differ} of {tri.size} pixels show "
                                 f"another triangle than a NumPy ray cast")
        same = (tri == ref_tri) & (ref_tri >= 0)
        err = np.abs(views.depth[same] - ref_depth[same]) / ref_depth[same]
        if not same.any() or float(np.median(err)) > 1e-4 or float(err.max()) > 1e-2:
            raise SelfTestFailed(f"render ({path} path): depth off by "
                                 f"{float(np.median(err)) if same.any() else float('nan'):.1e} "
                                 f"(median, relative) against a NumPy ray cast")
        want = np.where(ref_tri >= 0, mesh.face_material[np.maximum(ref_tri, 0)] + 1, 0)
        if np.count_nonzero((views.mat_id != want) & (tri == ref_tri)):
            raise SelfTestFailed(f"render ({path} path): material ids disagree with the "
                                 f"triangles' materials")


def check_canny(rt: Runtime) -> None:
    """Canny of two noise images, bit-identical to OpenCV."""
    import cv2

    rng = np.random.default_rng(5)
    imgs = rng.integers(0, 256, (2, 29, 41), dtype=np.uint8)
    imgs[1, :, :20] //= 8
    for l2 in (False, True):
        ours = canny(imgs, 40.0, 120.0, l2, runtime=rt)
        ref = np.stack([cv2.Canny(im, 40.0, 120.0, apertureSize=3, L2gradient=l2)
                        for im in imgs])
        differ = int(np.count_nonzero(ours != ref))
        if differ:
            raise SelfTestFailed(f"canny: {differ} pixels differ from OpenCV (l2={l2})")


def check_search(rt: Runtime) -> None:
    """Exact k-nearest search of 16 queries over 200 rows against NumPy distances."""
    rng = np.random.default_rng(9)
    db = rng.standard_normal((200, 24)).astype(np.float32)
    q = rng.standard_normal((16, 24)).astype(np.float32)
    idx, dist = FeatureIndex(db, runtime=rt).search(q, 5)
    ref = ((q.astype(np.float64)[:, None, :] - db[None].astype(np.float64)) ** 2).sum(-1)
    want = np.sort(ref, axis=1)[:, :5]
    got = np.take_along_axis(ref, np.asarray(idx, np.int64), axis=1)
    if not np.allclose(got, want, rtol=1e-4, atol=1e-4) or not np.allclose(
            np.asarray(dist, np.float64), want, rtol=1e-3, atol=1e-3):
        raise SelfTestFailed("search: the nearest rows or their distances differ from NumPy")


def _scene() -> Mesh:
    """Three triangles in the canonical unit sphere: two overlapping at different depths and
    one tilted, each its own material."""
    v = np.array([[-0.30, -0.20, 0.00], [0.30, -0.20, 0.05], [0.00, 0.30, -0.05],
                  [-0.10, -0.30, 0.15], [0.35, 0.00, -0.10], [0.05, 0.25, 0.20],
                  [-0.35, 0.05, -0.20], [-0.05, -0.05, 0.30], [-0.20, 0.30, 0.10]])
    faces = np.arange(9, dtype=np.uint32).reshape(3, 3)
    mats = [Material(name=f"m{i}") for i in range(3)]
    return Mesh(path="<selftest>", sha256="0" * 64, vertices=v, faces=faces,
                face_material=np.arange(3, dtype=np.uint16), materials=mats)


def _ray_cast(mesh: Mesh, K: np.ndarray, w2c: np.ndarray, width: int, height: int):
    """(V, H, W) nearest triangle id (-1: none) and camera depth z, by Moller-Trumbore through
    pixel centres (j + 0.5, i + 0.5); depth ties: the lower triangle id."""
    V = len(w2c)
    tri = np.full((V, height, width), -1, np.int64)
    depth = np.full((V, height, width), np.inf)
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    for view in range(V):
        d = np.stack([jj, ii, np.ones_like(jj)], -1) @ np.linalg.inv(K).T        # z = 1
        cam = mesh.vertices @ w2c[view][:3, :3].T + w2c[view][:3, 3]
        for f, (a, b, c) in enumerate(cam[mesh.faces.astype(np.int64)]):
            e1, e2 = b - a, c - a
            p = np.cross(d, e2)
            det = p @ e1
            ok = np.abs(det) > 1e-12
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            s = -a
            u = (p @ s) * inv
            qv = np.cross(s, e1)
            w = (d * qv).sum(-1) * inv
            t = (qv @ e2) * inv
            hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0) & (t < depth[view])
            depth[view][hit] = t[hit]
            tri[view][hit] = f
    return tri, depth
