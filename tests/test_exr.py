"""EXR view stacks: lossless round trip, headers, and the documented ray reconstruction."""
import json
import subprocess
import sys

import numpy as np
import pytest

from ucad_catalog.exr import read_viewset_exr, write_viewset_exr
from ucad_cl.cameras import make_ring
from ucad_cl.render import render_views
from tests.test_render import toy_car


def test_round_trip_and_documented_ray_reconstruction(runtime, tmp_path):
    import OpenEXR

    mesh = toy_car()
    mesh.file_to_norm = np.diag([0.5, 0.5, 0.5, 1.0])
    ring = make_ring(azimuth_step=60, elevations=(10.0, 40.0), size=(80, 64))
    views = render_views(mesh, ring)
    path = write_viewset_exr(tmp_path / "car.views.exr", views, mesh)
    back, meta = read_viewset_exr(path)
    for a in ("tri_id", "mat_id", "depth"):
        assert np.array_equal(getattr(back, a), getattr(views, a)), a
    assert np.array_equal(back.cameras.w2c, ring.w2c) and np.array_equal(back.cameras.K, ring.K)
    assert np.array_equal(back.cameras.azimuth, ring.azimuth)
    assert meta["materials"] == [m.name for m in mesh.materials]
    assert np.array_equal(meta["file_to_norm"], mesh.file_to_norm)
    # docs/FORMATS.md: recreate pixel rays and surface points from the header alone
    part = OpenEXR.File(str(path)).parts[3]
    K, w2c = part.header["ucad:K"], part.header["ucad:w2c"]
    (x0, y0), (x1, y1) = part.header["dataWindow"]
    W, H = part.header["displayWindow"][1] + 1
    assert (H, W) == (64, 80) and (x1 - x0 + 1) * (y1 - y0 + 1) < H * W    # only the object's box
    Z = np.full((H, W), np.inf, np.float32)
    Z[y0:y1 + 1, x0:x1 + 1] = part.channels["Z"].pixels
    tri = np.full((H, W), 0xFFFFFFFF, np.uint32)
    tri[y0:y1 + 1, x0:x1 + 1] = part.channels["tri"].pixels
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    R, t = w2c[:3, :3], w2c[:3, 3]
    d_cam = np.stack([j, i, np.ones_like(j)], -1) @ np.linalg.inv(K).T
    hit = np.isfinite(Z)
    points = ((d_cam * np.where(hit, Z, 0)[..., None]) - t) @ R
    # every reconstructed point lies on the plane of the triangle that the pixel shows
    fv = mesh.vertices[mesh.faces[tri[hit]]]
    n = np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dist = np.abs(np.einsum("ij,ij->i", points[hit] - fv[:, 0], n))
    # float32 depth + 1/256 px vertex snapping: micro-units of error in a unit-diagonal model
    assert np.median(dist) < 2e-5 and dist.max() < 1e-3


def test_reader_imports_no_opencl(tmp_path):
    code = ("import sys; sys.modules['pyopencl'] = None; import ucad_catalog.exr as e; "
            "print('ok')")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True).stdout.strip() == "ok"


def test_bad_files_give_clear_errors(tmp_path):
    bad = tmp_path / "x.views.exr"
    bad.write_bytes(b"not an exr")
    with pytest.raises(ValueError, match="x.views.exr"):
        read_viewset_exr(bad)


def test_empty_views_and_object_boxes_round_trip(runtime, tmp_path):
    """Views looking away from the model store a 1x1 background box; boxes touching the image
    border and views of one pixel come back exactly."""
    import OpenEXR

    from ucad_cl.artifacts import ViewSet

    rng = np.random.default_rng(5)
    V, H, W = 4, 9, 11
    mat = np.zeros((V, H, W), np.uint16)
    mat[1, 3, 4] = 2                                  # one pixel
    mat[2, :, -3:] = rng.integers(1, 4, (H, 3))       # touches top, bottom and right borders
    mat[3] = rng.integers(0, 4, (H, W))               # anywhere
    fg = mat > 0
    tri = np.where(fg, rng.integers(0, 1000, (V, H, W)), 0xFFFFFFFF).astype(np.uint32)
    depth = np.where(fg, rng.random((V, H, W)), np.inf).astype(np.float32)
    ring = make_ring(azimuth_step=90, elevations=(0.0,), size=(W, H))
    views = ViewSet(cameras=ring, tri_id=tri, mat_id=mat, depth=depth)
    path = write_viewset_exr(tmp_path / "v.views.exr", views, material_names=["a", "b", "c"])
    back, _ = read_viewset_exr(path)
    for a in ("tri_id", "mat_id", "depth"):
        assert np.array_equal(getattr(back, a), getattr(views, a)), a
    windows = [tuple(map(tuple, p.header["dataWindow"])) for p in OpenEXR.File(str(path)).parts]
    assert windows[0] == ((0, 0), (0, 0)) and windows[1] == ((4, 3), (4, 3))
    assert windows[2] == ((W - 3, 0), (W - 1, H - 1))


def _openexr_reference(path, views, names, f2n, sha):
    """The same view stack written by OpenEXR's own writer (the encoder before stop 34)."""
    import OpenEXR

    from ucad_catalog.exr import CONVENTIONS, FORMAT_VERSION, nonzero_box

    cams, parts = views.cameras, []
    H, W = views.mat_id.shape[1:]
    for v in range(views.n_views):
        y0, y1, x0, x1 = nonzero_box(views.mat_id[v]) or (0, 1, 0, 1)
        header = {
            "dataWindow": (np.array([x0, y0], np.int32), np.array([x1 - 1, y1 - 1], np.int32)),
            "displayWindow": (np.array([0, 0], np.int32), np.array([W - 1, H - 1], np.int32)),
            "compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
            "ucad:formatVersion": FORMAT_VERSION, "ucad:K": np.asarray(cams.K, np.float64),
            "ucad:w2c": np.asarray(cams.w2c[v], np.float64),
            "worldToCamera": np.asarray(cams.w2c[v], np.float32), "ucad:fileToNorm": f2n,
            "ucad:view": v, "ucad:azimuth": float(cams.azimuth[v]),
            "ucad:elevation": float(cams.elevation[v]), "ucad:distance": float(cams.distance),
            "ucad:near": float(cams.near), "ucad:meshSha256": sha,
            "ucad:conventions": CONVENTIONS}
        if v == 0:
            header["ucad:materials"] = json.dumps(names, ensure_ascii=False)
        box = (slice(y0, y1), slice(x0, x1))
        channels = {"tri": OpenEXR.Channel(np.ascontiguousarray(views.tri_id[v][box], np.uint32)),
                    "mat": OpenEXR.Channel(np.ascontiguousarray(views.mat_id[v][box], np.uint32)),
                    "Z": OpenEXR.Channel(np.ascontiguousarray(views.depth[v][box], np.float32))}
        parts.append(OpenEXR.Part(header, channels, f"view_{v:03d}"))
    OpenEXR.File(parts).write(str(path))


def test_encoder_writes_openexrs_headers_and_chunks_openexr_decodes(runtime, tmp_path):
    """Our encoder against OpenEXR's writer and reader: the same headers to the byte (every
    attribute, the part list's end), the same chunk count per part; OpenEXR decodes every pixel
    of ours; a chunk deflate cannot shrink (a one-pixel view: 12 bytes) is stored plain, and
    the stack is byte-identical when written again."""
    import OpenEXR

    from ucad_catalog.exr import ViewStackFile

    mesh = toy_car()
    mesh.materials[0].name = "peinture métallisée"          # non-ASCII names: UTF-8, sized
    f2n = np.diag([0.5, 2.0, 0.5, 1.0])
    mesh.file_to_norm = f2n
    ring = make_ring(azimuth_step=45, elevations=(15.0, 5.0), size=(96, 72))
    views = render_views(mesh, ring)
    views.mat_id[5] = 0                                       # an empty view
    views.tri_id[5] = 0xFFFFFFFF
    views.depth[5] = np.inf
    ours = write_viewset_exr(tmp_path / "ours.exr", views, mesh)
    ref = tmp_path / "ref.exr"
    _openexr_reference(ref, views, [m.name for m in mesh.materials], f2n, mesh.sha256)
    a, b = ours.read_bytes(), ref.read_bytes()
    sa, sb = ViewStackFile(ours), ViewStackFile(ref)
    n_chunks = [len(p["offsets"]) for p in sa.parts]
    assert n_chunks == [len(p["offsets"]) for p in sb.parts]
    head = int(sb.parts[0]["offsets"][0]) - 8 * sum(n_chunks)   # the offset tables start here
    assert head == int(sa.parts[0]["offsets"][0]) - 8 * sum(n_chunks)
    assert a[:head] == b[:head]
    parts = OpenEXR.File(str(ours), separate_channels=True).parts
    for v, part in enumerate(parts):
        (x0, y0), (x1, y1) = part.header["dataWindow"]
        box = (slice(y0, y1 + 1), slice(x0, x1 + 1))
        assert np.array_equal(part.channels["tri"].pixels, views.tri_id[v][box])
        assert np.array_equal(part.channels["mat"].pixels, views.mat_id[v][box].astype(np.uint32))
        assert np.array_equal(part.channels["Z"].pixels, views.depth[v][box])
        assert part.header["ucad:azimuth"] == ring.azimuth[v]
    at = int(sa.parts[5]["offsets"][0])                      # the empty view: one plain chunk
    assert int.from_bytes(a[at + 8:at + 12], "little") == 12
    assert a[at + 12:at + 24] == np.array([[np.inf]], "<f4").tobytes() + bytes(4) + b"\xff" * 4
    assert write_viewset_exr(tmp_path / "again.exr", views, mesh).read_bytes() == a
