"""Shaded RGB images from rendered triangle-id maps: Lambert + Blinn-Phong, flat per face.

``shade_views(mesh, views)`` turns the rasterizer's ``tri_id`` maps (see ``ucad_cl/artifacts.py``) into
(V, H, W, 3) uint8 sRGB images. Used to compute pose features of renders and to make synthetic
reference photos.

Conventions and units:

* Colours: per-material albedo in *linear* RGB [0, 1] (default ``Material.base_color[:3]``); the
  shaded linear value is encoded to sRGB (IEC 61966-2-1 curve) and rounded to uint8.
* Light: a directional light, ``light_dir`` points from the surface *toward* the light and is
  given in the camera frame (x right, y down, z forward), so a light "over the viewer's left
  shoulder" is (-0.4, -0.6, -1). The light moves with the camera: every view is lit alike.
* Normals: one per face, ``(v1 - v0) x (v2 - v0)`` normalised, in the canonical frame; meshes are
  two-sided, so each face normal is flipped to face the camera in every view. Degenerate faces
  (zero normal) get ambient light only.
* Shading: ``albedo * (ambient + (1 - ambient) * max(n.l, 0)) + specular * max(n.h, 0)^shininess``
  with ``h = normalize(l + v)`` and ``v`` the unit vector from the pixel's surface point to the
  camera (per pixel, from the pixel ray).
* Background: an RGB triple of uint8 values, or an image (H, W, 3) / (V, H, W, 3) uint8.

Two paths: ``device=True`` (default) runs ``ucad_cl/kernels/shade.cl`` over all views in one launch
(float32; measured ~0.15 s -> ~0.01 s for 72 views x 256 px, where NumPy shading was the largest
cost of a catalogue build), after a launch that computes every pixel's half vector once (the
same in every view: 144 views of a 50k-triangle mesh ~66 -> ~40 ms on PoCL, same bytes); on CPUs
``shade_pixels16`` shades 16 pixels a work-item in vector code, into the page-aligned output in
place (~41 -> ~31 ms, same bytes);
``device=False`` is the vectorised float64 NumPy reference, one view at a time, which the kernel
is tested against (to within one 8-bit level).
"""
from __future__ import annotations

import functools
from typing import Sequence

import numpy as np

from .abi import SHADE_PARAMS, SRGB_BUCKETS
from .artifacts import BACKGROUND_TRI, Mesh, ViewSet
from .runtime import Runtime, aligned_empty, get_runtime

DEFAULT_LIGHT = (-0.4, -0.6, -1.0)


def shade_views(mesh: Mesh, views: ViewSet, *, colors: np.ndarray | Sequence | None = None,
                light_dir: Sequence[float] = DEFAULT_LIGHT, ambient: float = 0.3,
                specular: float = 0.25, shininess: float = 32.0,
                background: Sequence[int] | np.ndarray = (0, 0, 0),
                device: bool = True, runtime: Runtime | None = None,
                normals: np.ndarray | None = None, lanes: int | None = None) -> np.ndarray:
    """(V, H, W, 3) uint8 sRGB images of ``views`` (rendered from ``mesh``), on ``runtime``
    (default ``get_runtime()``) unless ``device`` is False (NumPy). ``normals``: the mesh's
    ``face_normals`` when the caller already has them (shading many view sets). ``lanes``:
    pixels a work-item shades, 16 (``shade_pixels16``, vector code) or 1 (``shade_pixels``);
    None picks 16 on CPU devices, 1 on others. Both give the same bytes; 16 needs an integer
    shininess in [1, 1024] and views of a multiple of 16 pixels, and falls back to 1 otherwise."""
    V, H, W = views.tri_id.shape
    albedo = _albedo(mesh, colors)
    bg = _background(background, V, H, W)
    if not 0.0 <= ambient <= 1.0:
        raise ValueError(f"ambient={ambient} must be in [0, 1]")
    if specular < 0.0 or shininess <= 0.0:
        raise ValueError(f"specular={specular} must be >= 0 and shininess={shininess} > 0")
    if lanes not in (None, 1, 16):
        raise ValueError(f"lanes must be 1, 16 or None, got {lanes!r}")
    light = np.asarray(light_dir, np.float64)
    if light.shape != (3,) or not np.all(np.isfinite(light)) or not np.linalg.norm(light) > 0:
        raise ValueError(f"light_dir must be a finite non-zero 3-vector, got {light_dir!r}")
    light = light / np.linalg.norm(light)

    if normals is None:
        normals = face_normals(mesh)                                 # (F, 3) canonical frame
    v0 = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)[:, 0]]
    fmat = np.asarray(mesh.face_material, np.int64)
    cam = views.cameras
    if device and V * H * W > 0:
        return _shade_device(runtime or get_runtime(), views, normals, v0, mesh.face_material,
                             albedo, light, ambient, specular, shininess, bg, lanes)
    # per pixel (same for every view): unit vector to the camera v = -K^-1 (j+.5, i+.5, 1) / |.|
    # and the Blinn-Phong half vector h = normalize(l + v)
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    rays = np.stack([j, i, np.ones_like(j)], -1) @ np.linalg.inv(cam.K).T
    half = light - rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    half = half.reshape(-1, 3)
    degenerate = ~np.any(normals != 0.0, axis=1)
    out = np.empty((V, H, W, 3), np.uint8)
    for v in range(V):
        R, t = cam.w2c[v, :3, :3], cam.w2c[v, :3, 3]
        n_cam = normals @ R.T                                        # (F, 3)
        p0 = v0 @ R.T + t                                            # a point of each face
        n_cam *= np.where(np.einsum("fk,fk->f", n_cam, p0) > 0.0, -1.0, 1.0)[:, None]
        diffuse = np.maximum(n_cam @ light, 0.0)
        lit = albedo[fmat] * (ambient + (1.0 - ambient) * diffuse)[:, None]   # (F, 3)
        fg = np.flatnonzero(views.tri_id[v].reshape(-1) != BACKGROUND_TRI)
        f = views.tri_id[v].reshape(-1)[fg].astype(np.int64)
        spec = specular * np.maximum(np.einsum("pk,pk->p", n_cam[f], half[fg]), 0.0) ** shininess
        spec[degenerate[f]] = 0.0
        img = bg[v if bg.shape[0] > 1 else 0].reshape(-1, 3).copy()
        img[fg] = linear_to_srgb8(lit[f] + spec[:, None])
        out[v] = img.reshape(H, W, 3)
    return out




def _shade_device(rt: Runtime, views, normals, v0, face_material, albedo, light, ambient,
                  specular, shininess, bg, lanes: int | None) -> np.ndarray:
    import pyopencl as cl

    V, H, W = views.tri_id.shape
    cam = views.cameras
    uniform_bg = bg.shape[0] == 1 and bool(np.all(bg[0] == bg[0, 0, 0]))
    prm = np.zeros(1, SHADE_PARAMS)
    prm["kinv"] = np.linalg.inv(cam.K).reshape(9)
    prm["light"] = light
    prm["ambient"], prm["specular"], prm["shininess"] = ambient, specular, shininess
    prm["width"], prm["height"], prm["n_views"] = W, H, V
    prm["int_shininess"] = int(shininess) if float(shininess).is_integer() and 1 <= shininess <= 1024 else 0
    prm["bg"] = bg[0, 0, 0] if uniform_bg else 0
    mf = cl.mem_flags
    ctx, q = rt.ctx, rt.queue

    def buf(a, dtype):
        a = np.ascontiguousarray(a, dtype)
        return cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a if a.size else np.zeros(1, dtype))

    # the maps in place (no copy on PoCL: render_views' are page-aligned), the output in a
    # scratch buffer reused across calls (no allocation and first touch per call)
    tri = np.ascontiguousarray(views.tri_id, np.uint32)
    d_tri = cl.Buffer(ctx, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=tri)
    d_w2c = buf(cam.w2c[:, :3, :].reshape(V, 12), np.float32)
    d_n, d_v0 = buf(normals, np.float32), buf(v0, np.float32)
    d_fm, d_alb = buf(face_material, np.uint16), buf(albedo, np.float32)
    # written in place (page-aligned: no copy on PoCL; a map makes it current on any device)
    out = aligned_empty((V, H, W, 3), np.uint8)
    d_out = cl.Buffer(ctx, mf.WRITE_ONLY | mf.USE_HOST_PTR, hostbuf=out)
    d_half = rt.scratch("shade.half", 12 * H * W)
    kh = rt.kernel("shade", "half_vectors")
    kh.set_args(prm, d_half)
    cl.enqueue_nd_range_kernel(q, kh, ((H * W + 255) // 256 * 256,), (256,))
    # CPUs: 16 pixels a work-item in vector code (same bytes; integer shininess, views of a
    # multiple of 16 pixels); else, and on GPUs, one pixel a work-item
    n = V * H * W
    if lanes is None:
        lanes = 16 if rt.device.type & cl.device_type.CPU else 1
    if prm["int_shininess"][0] == 0 or (H * W) % 16:
        lanes = 1
    k = rt.kernel("shade", "shade_pixels16" if lanes == 16 else "shade_pixels")
    d_thr = buf(srgb8_thresholds(), np.float32)
    d_start = buf(srgb8_bucket_start(), np.uint8)
    k.set_args(d_tri, d_w2c, d_n, d_v0, d_fm, d_alb, d_thr, d_start, d_half, prm, d_out)
    items = -(-n // lanes)
    cl.enqueue_nd_range_kernel(q, k, ((items + 255) // 256 * 256,), (256,))
    view, _ = cl.enqueue_map_buffer(q, d_out, cl.map_flags.READ, 0, (d_out.size,), np.uint8)
    view.base.release(q)
    q.finish()
    d_out.release()
    if not uniform_bg:
        bgmask = views.tri_id == BACKGROUND_TRI
        out[bgmask] = np.broadcast_to(bg, (V, H, W, 3))[bgmask]
    return out


@functools.lru_cache(maxsize=1)
def srgb8_thresholds() -> np.ndarray:
    """(255,) float32: the smallest float32 linear value giving sRGB level k = 1..255 under
    :func:`linear_to_srgb8` (found by bisection on float32 values, so a comparison with them
    gives exactly the level ``linear_to_srgb8`` computes in float64 for float32 inputs)."""
    k = np.arange(1, 256)
    lo = np.zeros(255, np.float32)                          # level(lo) < k <= level(hi)
    hi = np.ones(255, np.float32)
    while True:                                             # every level bisected at once
        mid = ((lo.astype(np.float64) + hi.astype(np.float64)) / 2).astype(np.float32)
        open_ = (mid != lo) & (mid != hi)
        if not open_.any():
            return hi
        up = linear_to_srgb8(mid.astype(np.float64)) >= k
        hi = np.where(open_ & up, mid, hi)
        lo = np.where(open_ & ~up, mid, lo)




@functools.lru_cache(maxsize=1)
def srgb8_bucket_start() -> np.ndarray:
    """(SRGB_BUCKETS,) uint8: a lower bound of the sRGB level of every value in each bucket
    ``b = int(x * (SRGB_BUCKETS - 1))`` (x in [0, 1]): the level at the start of bucket b - 1, so
    float rounding in the bucket index never makes it too high; the kernel then steps up with
    ``srgb8_thresholds``."""
    lo = np.maximum(np.arange(SRGB_BUCKETS) - 1, 0) / (SRGB_BUCKETS - 1)
    return np.searchsorted(srgb8_thresholds(), lo.astype(np.float32), side="right").astype(np.uint8)


def face_normals(mesh: Mesh) -> np.ndarray:
    """(F, 3) float64 unit face normals ``(v1-v0) x (v2-v0)``; zero for degenerate faces."""
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def linear_to_srgb8(lin: np.ndarray) -> np.ndarray:
    """Linear RGB (any shape, values clipped to [0, 1]) -> sRGB uint8, round half up."""
    x = np.clip(lin, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.floor(s * 255.0 + 0.5).astype(np.uint8)


def _albedo(mesh: Mesh, colors) -> np.ndarray:
    n_mat = max(len(mesh.materials), int(np.max(np.asarray(mesh.face_material, np.int64), initial=-1)) + 1)
    if colors is None:
        cols = [m.base_color[:3] for m in mesh.materials]
        cols += [(0.8, 0.8, 0.8)] * (n_mat - len(cols))
        return np.asarray(cols, np.float64).reshape(n_mat, 3)
    c = np.asarray(colors, np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] < n_mat:
        raise ValueError(f"colors must be (n_materials={n_mat}, 3) linear RGB, got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("colors contain NaN or infinity")
    return c


def _background(background, V: int, H: int, W: int) -> np.ndarray:
    b = np.asarray(background)
    if b.shape == (3,):
        if np.any(b < 0) or np.any(b > 255):
            raise ValueError(f"background colour {background!r} must be uint8 values 0..255")
        return np.broadcast_to(b.astype(np.uint8), (1, H, W, 3))
    if b.dtype != np.uint8:
        raise ValueError(f"background image must be uint8, got {b.dtype}")
    if b.shape == (H, W, 3):
        return b[None]
    if b.shape == (V, H, W, 3):
        return b
    raise ValueError(f"background must be (3,), ({H}, {W}, 3) or ({V}, {H}, {W}, 3), "
                     f"got {b.shape}")


def shade_stored_view(depth: np.ndarray, mat_id: np.ndarray, tri_id: np.ndarray, K: np.ndarray,
                      albedo: np.ndarray, *, light_dir: Sequence[float] = DEFAULT_LIGHT,
                      ambient: float = 0.3, specular: float = 0.25, shininess: float = 32.0,
                      background: Sequence[int] = (128, 128, 128)) -> np.ndarray:
    """(H, W, 3) uint8 sRGB image of one stored view shaded as ``shade_views`` shades it, without
    the mesh: from its maps (``depth`` (H, W) linear camera depth, +inf background; ``mat_id``
    material index + 1; ``tri_id`` face index) and ``K``; ``albedo`` (M + 1, 3) linear RGB per
    material id (row 0 unused). Face normals are recovered from the depth map: the central
    differences of the back-projected points at pixels whose four neighbours lie on the same
    face are exact, and each face takes their mean; a face without such a pixel (under a few
    pixels) takes its pixels' own central differences (neighbours off the vehicle count as the
    pixel itself). Normals face the camera; light, ambient, Blinn-Phong as ``shade_views``."""
    depth = np.asarray(depth, np.float64)
    H, W = depth.shape
    out = np.empty((H, W, 3), np.uint8)
    out[:1] = np.asarray(background, np.uint8)
    out[1:] = out[:1]                               # (a row copied down: ~50x a 3-value broadcast)
    finite = np.isfinite(depth)
    rows = np.flatnonzero(finite.any(axis=1))
    if rows.size == 0:
        return out
    cols = np.flatnonzero(finite.any(axis=0))
    r0, c0 = int(rows[0]), int(cols[0])
    fgp = np.pad(finite[r0:rows[-1] + 1, c0:cols[-1] + 1], 1)   # the vehicle's box, padded
    wp = fgp.shape[1]
    at = np.flatnonzero(fgp)                        # the vehicle's pixels, flat in fgp
    i, j = np.divmod(at, wp)
    q = (i + (r0 - 1)) * W + (j + (c0 - 1))         # ... and flat in the view
    Kinv = np.linalg.inv(np.asarray(K, np.float64))
    pix = np.stack([j + (c0 - 1 + 0.5), i + (r0 - 1 + 0.5), np.ones(at.size)], -1)
    p = pix @ Kinv.T * depth.ravel()[q][:, None]   # the back-projected points
    row = np.full(fgp.size, -1, np.int64)           # fgp's pixel -> its row of p (-1: off)
    row[at] = np.arange(at.size)
    tri = np.pad(np.asarray(tri_id)[r0:rows[-1] + 1, c0:cols[-1] + 1].astype(np.int64), 1,
                 constant_values=-1).ravel()
    t = tri[at]
    own = np.arange(at.size)
    pts, same = [], np.ones(at.size, bool)
    for step in (1, -1, wp, -wp):                   # right, left, below, above
        k = row[at + step]
        pts.append(np.take(p, np.where(k >= 0, k, own), axis=0))   # off-vehicle: the pixel
        same &= tri[at + step] == t
    a, b = pts[0] - pts[1], pts[2] - pts[3]
    nf = np.empty_like(p)                           # a x b, as np.cross computes it
    nf[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    nf[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    nf[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    nf /= np.maximum(_norms(nf), 1e-300)
    f, n_faces = _face_groups(t)
    if same.any():
        acc = np.stack([np.bincount(f[same], weights=nf[same, c], minlength=n_faces)
                        for c in range(3)], -1)
        has = np.bincount(f[same], minlength=n_faces)[f] > 0
        nf[has] = acc[f[has]]
    nf /= np.maximum(_norms(nf), 1e-300)
    nf *= np.where(np.einsum("pk,pk->p", nf, p) > 0.0, -1.0, 1.0)[:, None]
    light = np.asarray(light_dir, np.float64)
    light = light / np.linalg.norm(light)
    v = -p / _norms(p)
    half = light + v
    half /= _norms(half)
    alb = np.asarray(albedo, np.float64)
    base = alb[np.minimum(np.asarray(mat_id).ravel()[q].astype(np.int64), len(alb) - 1)]
    diffuse = np.maximum(nf @ light, 0.0)
    nh = np.einsum("pk,pk->p", nf, half)
    lit = np.flatnonzero(~(nh <= 0.0))              # max(n.h, 0)^shininess: 0 elsewhere (NaN kept)
    spec = np.zeros(at.size)
    spec[lit] = specular * np.take(nh, lit) ** shininess
    out.reshape(-1, 3)[q] = linear_to_srgb8(base * (ambient + (1.0 - ambient) * diffuse)[:, None]
                                            + spec[:, None])
    return out


def _face_groups(t: np.ndarray) -> tuple[np.ndarray, int]:
    """(group of each pixel, number of groups): pixels of one face (``t``, (N,) int64 face
    indices) share a group. The groups are ``t - min(t)`` when that span is small (no sort),
    else ``np.unique``'s; either way a ``np.bincount`` over them adds each face's pixels in
    pixel order, so the sums are the same bits."""
    lo, hi = int(t.min()), int(t.max())
    if hi - lo <= 16 * t.size + 4096:
        return t - lo, hi - lo + 1
    faces, f = np.unique(t, return_inverse=True)
    return f.reshape(-1), faces.size


def _norms(x: np.ndarray) -> np.ndarray:
    """(N, 1) Euclidean lengths of the rows of ``x`` (N, 3): sqrt((x0^2 + x1^2) + x2^2), the
    sums in that order (NumPy 2.4's ``linalg.norm(x, axis=-1)`` gives the same bits at ~6x the
    time: its reduction over an axis of 3)."""
    s = x * x
    return np.sqrt((s[:, 0] + s[:, 1]) + s[:, 2])[:, None]

