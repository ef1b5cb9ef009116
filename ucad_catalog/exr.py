"""The per-mesh view stack: one multi-part OpenEXR file, one part per view (format version 2).

Every part ``view_VVV`` (scanline, ZIP compressed) has the display window of the whole H x W
image and a *data window* that is the bounding box of the object's pixels in that view (1 x 1 at
the top-left corner, holding background, when the view is empty). Pixels outside the data window
are background. (Version 1 stored the whole image; at 256 px the object's box is ~28 % of a view
on average, and OpenEXR's write cost grows with the pixels stored: 150 -> ~50 ms per mesh of
72 views.) Three channels:

=======  =====  =====================================================================
channel  type   meaning
=======  =====  =====================================================================
``tri``  UINT   triangle (face) index after ingest; 0xFFFFFFFF = background
``mat``  UINT   material id = material index + 1; 0 = background
``Z``    FLOAT  linear camera-space depth z in canonical units; +inf = background
=======  =====  =====================================================================

and these header attributes (all parts, unless noted):

* ``ucad:K`` (m33d): intrinsics, OpenCV convention, pixel (i, j) centred at (j + 0.5, i + 0.5);
* ``ucad:w2c`` (m44d): world-to-camera, world = the canonical frame, camera x right, y down,
  z forward; ``worldToCamera`` (m44f, the standard EXR attribute) holds the same matrix;
* ``ucad:fileToNorm`` (m44d): file frame -> canonical frame, so file-frame rays are recoverable;
* ``ucad:view`` (int), ``ucad:azimuth`` / ``ucad:elevation`` (float, degrees),
  ``ucad:distance`` / ``ucad:near`` (float, canonical units);
* ``dataWindow`` / ``displayWindow`` (box2i, standard): the stored box and the whole image;
* ``ucad:formatVersion`` (int), ``ucad:meshSha256`` (string), ``ucad:conventions`` (string);
* part 0 only: ``ucad:materials`` (string, JSON list of material names, index = id - 1).

The ray of pixel (i, j) in the canonical frame: origin ``-R^T t``, direction
``R^T K^-1 (j + 0.5, i + 0.5, 1)`` with ``w2c = [R t; 0 1]``; the surface point is
``origin + direction * Z / (direction . R[2])``. See ``read_viewset_exr`` and docs/FORMATS.md.
This module imports no OpenCL.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

FORMAT_VERSION = 2
BACKGROUND = {"tri": np.uint32(0xFFFFFFFF), "mat": np.uint32(0), "Z": np.float32(np.inf)}
CONVENTIONS = ("canonical frame: right-handed, +Y up, front +X, right side +Z, bbox centred "
               "(z on the mirror plane when symmetric), bbox diagonal 1; "
               "camera: OpenCV (x right, y down, z forward), pixel (i,j) centre at (j+0.5,i+0.5); "
               "azimuth 0 looks from +X (the front view), counter-clockwise seen from +Y; "
               "mat = material index + 1 (0 background), tri = face index (0xFFFFFFFF background), "
               "Z = linear camera depth (+inf background)")


def write_viewset_exr(path, views, mesh=None, *, material_names=None, file_to_norm=None,
                      mesh_sha256: str | None = None) -> Path:
    """Write ``views`` (a ViewSet) to ``path`` atomically (temporary name, then rename)."""
    import OpenEXR

    path = Path(path)
    cams = views.cameras
    names = material_names if material_names is not None else (
        [m.name for m in mesh.materials] if mesh is not None else [])
    f2n = np.asarray(file_to_norm if file_to_norm is not None else (
        mesh.file_to_norm if mesh is not None else np.eye(4)), np.float64)
    sha = mesh_sha256 or (mesh.sha256 if mesh is not None else "")
    from ucad_cl.artifacts import nonzero_box

    parts = []
    H, W = views.mat_id.shape[1:]
    display = (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32))
    for v in range(views.n_views):
        # the object's box (material id > 0); an empty view stores its top-left pixel
        y0, y1, x0, x1 = nonzero_box(views.mat_id[v]) or (0, 1, 0, 1)
        header = {
            "dataWindow": (np.array([x0, y0], np.int32), np.array([x1 - 1, y1 - 1], np.int32)),
            "displayWindow": display,
            "compression": OpenEXR.ZIP_COMPRESSION,
            "type": OpenEXR.scanlineimage,
            "ucad:formatVersion": FORMAT_VERSION,
            "ucad:K": np.asarray(cams.K, np.float64),
            "ucad:w2c": np.asarray(cams.w2c[v], np.float64),
            "worldToCamera": np.asarray(cams.w2c[v], np.float32),
            "ucad:fileToNorm": f2n,
            "ucad:view": v,
            "ucad:azimuth": float(cams.azimuth[v]),
            "ucad:elevation": float(cams.elevation[v]),
            "ucad:distance": float(cams.distance),
            "ucad:near": float(cams.near),
            "ucad:meshSha256": sha,
            "ucad:conventions": CONVENTIONS,
        }
        if v == 0:
            header["ucad:materials"] = json.dumps(list(names), ensure_ascii=False)
        box = (slice(y0, y1), slice(x0, x1))
        channels = {
            "tri": OpenEXR.Channel(np.ascontiguousarray(views.tri_id[v][box], np.uint32)),
            "mat": OpenEXR.Channel(np.ascontiguousarray(views.mat_id[v][box], np.uint32)),
            "Z": OpenEXR.Channel(np.ascontiguousarray(views.depth[v][box], np.float32)),
        }
        parts.append(OpenEXR.Part(header, channels, f"view_{v:03d}"))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        OpenEXR.File(parts).write(str(tmp))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _full_image(part, name: str, dtype) -> np.ndarray:
    """A channel of ``part`` placed in its display window, background outside the data window."""
    (dx0, dy0), (dx1, dy1) = (np.asarray(c) for c in part.header["displayWindow"])
    (x0, y0), (x1, y1) = (np.asarray(c) for c in part.header["dataWindow"])
    out = np.full((int(dy1 - dy0) + 1, int(dx1 - dx0) + 1), BACKGROUND[name], dtype)
    out[y0 - dy0:y1 - dy0 + 1, x0 - dx0:x1 - dx0 + 1] = part.channels[name].pixels
    return out


def read_viewset_exr(path):
    """Read a view stack back: ``(ViewSet, meta)`` with meta keys ``materials``,
    ``file_to_norm``, ``mesh_sha256``, ``format_version``. Raises ValueError naming the file."""
    import OpenEXR

    from ucad_cl.artifacts import CameraRing, ViewSet

    path = Path(path)
    try:
        f = OpenEXR.File(str(path))
    except Exception as exc:
        raise ValueError(f"{path}: not a readable OpenEXR view stack ({exc})") from exc
    parts = f.parts
    if not parts or "ucad:w2c" not in parts[0].header:
        raise ValueError(f"{path}: OpenEXR file without ucad view headers")
    h0 = parts[0].header
    try:
        tri = np.stack([_full_image(p, "tri", np.uint32) for p in parts])
        mat = np.stack([_full_image(p, "mat", np.uint16) for p in parts])
        depth = np.stack([_full_image(p, "Z", np.float32) for p in parts])
    except (KeyError, ValueError) as exc:
        raise ValueError(f"{path}: view stack parts lack channel or window data ({exc})") from exc
    ring = CameraRing(
        K=np.asarray(h0["ucad:K"], np.float64),
        w2c=np.stack([np.asarray(p.header["ucad:w2c"], np.float64) for p in parts]),
        width=int(tri.shape[2]), height=int(tri.shape[1]),
        azimuth=np.array([p.header["ucad:azimuth"] for p in parts], np.float64),
        elevation=np.array([p.header["ucad:elevation"] for p in parts], np.float64),
        distance=float(h0["ucad:distance"]), near=float(h0["ucad:near"]))
    meta = {
        "materials": json.loads(h0.get("ucad:materials", "[]")),
        "file_to_norm": np.asarray(h0["ucad:fileToNorm"], np.float64),
        "mesh_sha256": h0.get("ucad:meshSha256", ""),
        "format_version": int(h0.get("ucad:formatVersion", 0)),
    }
    return ViewSet(cameras=ring, tri_id=tri, mat_id=mat, depth=depth), meta
