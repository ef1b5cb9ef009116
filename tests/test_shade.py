"""Shading: against an independent per-pixel computation (Embree hits + trimesh normals)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from ucad_cl.cameras import make_ring
from ucad_cl.render import render_views
from ucad_cl.shade import linear_to_srgb8, shade_stored_view, shade_views
from ucad_cl.artifacts import Material, Mesh

pytestmark = pytest.mark.every_device      # tests/conftest.py: UCAD_TEST_DEVICES


def _mesh(tm: trimesh.Trimesh, fmat, colors) -> Mesh:
    v = tm.vertices - tm.bounds.mean(axis=0)
    v = v / np.linalg.norm(tm.bounds[1] - tm.bounds[0])
    return Mesh(path="shade-test", sha256="0" * 64, vertices=v,
                faces=np.asarray(tm.faces, np.uint32), face_material=np.asarray(fmat, np.uint16),
                materials=[Material(f"m{i}", base_color=(*c, 1.0)) for i, c in enumerate(colors)])


def _scene() -> Mesh:
    box = trimesh.creation.box((1.0, 0.4, 0.5))
    ball = trimesh.creation.icosphere(2, radius=0.15)
    ball.apply_translation((0.3, 0.3, 0.0))
    tm = trimesh.util.concatenate([box, ball])
    fmat = np.r_[np.zeros(len(box.faces)), np.ones(len(ball.faces))]
    return _mesh(tm, fmat, [(0.8, 0.2, 0.1), (0.1, 0.3, 0.9)])


def _expected(mesh, ring, tri, light, ambient, specular, shininess, bg):
    """Formula of shade.py's docstring, evaluated per pixel from trimesh's face normals."""
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    normals = tm.face_normals
    light = np.asarray(light, float) / np.linalg.norm(light)
    albedo = np.array([m.base_color[:3] for m in mesh.materials])
    out = np.empty(tri.shape + (3,), np.uint8)
    for v in range(ring.n_views):
        R, t = ring.w2c[v, :3, :3], ring.w2c[v, :3, 3]
        cam_pos = -R.T @ t
        img = np.tile(np.asarray(bg, np.uint8), tri.shape[1:] + (1,))
        for i, j in zip(*np.nonzero(tri[v] >= 0)):
            f = tri[v, i, j]
            n = R @ normals[f]
            centroid = R @ tm.triangles_center[f] + t
            if n @ centroid > 0:                                  # face the camera
                n = -n
            ray = np.linalg.inv(ring.K) @ [j + 0.5, i + 0.5, 1.0]
            view = -ray / np.linalg.norm(ray)
            h = (light + view) / np.linalg.norm(light + view)
            lin = (albedo[mesh.face_material[f]] * (ambient + (1 - ambient) * max(n @ light, 0))
                   + specular * max(n @ h, 0) ** shininess)
            img[i, j] = linear_to_srgb8(lin)
        out[v] = img
        assert np.isfinite(cam_pos).all()
    return out


def test_shading_matches_independent_per_pixel_reference(runtime):
    pytest.importorskip("embreex")
    from tests.reference import raycast_views

    mesh = _scene()
    ring = make_ring(60.0, (20.0, -10.0), size=40)
    views = render_views(mesh, ring, runtime=runtime)
    kw = dict(light_dir=(0.3, -0.7, -1.0), ambient=0.2, specular=0.4, shininess=16.0)
    got = shade_views(mesh, views, background=(10, 20, 30), **kw, runtime=runtime)
    tri_ref, _, _ = raycast_views(mesh, ring)
    agree = tri_ref == np.where(views.tri_id == 0xFFFFFFFF, -1, views.tri_id.astype(np.int64))
    assert agree.mean() > 0.98
    want = _expected(mesh, ring, tri_ref, kw["light_dir"], kw["ambient"], kw["specular"],
                     kw["shininess"], (10, 20, 30))
    diff = np.abs(got.astype(int) - want.astype(int)).max(axis=-1)
    assert diff[agree].max() <= 1                                 # rounding at .5 only
    assert (got[views.tri_id == 0xFFFFFFFF] == (10, 20, 30)).all()


def test_stored_view_shading_without_the_mesh_matches_shade_views(runtime):
    """``shade_stored_view`` recovers face normals from the depth map alone (what a catalogue
    stores): the box's large faces come out as ``shade_views`` shades them from the mesh; the
    sphere's small faces (a few pixels each) may be a few levels off."""
    mesh = _scene()
    ring = make_ring(45.0, (15.0,), size=96)
    views = render_views(mesh, ring, runtime=runtime)
    kw = dict(light_dir=(-0.4, -0.6, -1.0), ambient=0.3, specular=0.25, shininess=32.0)
    want = shade_views(mesh, views, background=(128, 128, 128), **kw, runtime=runtime)
    albedo = np.array([(0.8, 0.8, 0.8)] + [m.base_color[:3] for m in mesh.materials])
    box_faces = 12                                         # trimesh's box: the first 12 faces
    for v in range(ring.n_views):
        got = shade_stored_view(views.depth[v], views.mat_id[v], views.tri_id[v], ring.K,
                                albedo, **kw)
        fg = np.isfinite(views.depth[v])
        assert (got[~fg] == 128).all()
        diff = np.abs(got.astype(int) - want[v].astype(int)).max(axis=-1)
        on_box = fg & (views.tri_id[v].astype(np.int64) < box_faces)
        assert np.mean(diff[on_box] <= 1) > 0.99, v
        assert np.mean(diff[fg] <= 4) > 0.9, v


def _stored_view_by_definition(depth, mat_id, tri_id, K, albedo, light, ambient, specular,
                               shininess, bg):
    """``shade_stored_view``'s docstring, pixel by pixel in Python floats: the back-projected
    point of each pixel, its central differences (a neighbour off the vehicle or the image
    counts as the pixel), each face's mean over its pixels whose four neighbours lie on it."""
    H, W = depth.shape
    Ki = np.linalg.inv(K).tolist()
    fg = np.isfinite(depth)

    def point(i, j):
        x = (j + 0.5, i + 0.5, 1.0)
        return [depth[i, j] * sum(Ki[r][c] * x[c] for c in range(3)) for r in range(3)]

    def unit(a):
        n = math.sqrt(sum(c * c for c in a))
        return [c / n for c in a] if n > 0 else [0.0, 0.0, 0.0]

    own, sums = {}, {}
    for i, j in zip(*np.nonzero(fg)):
        near = [(i, j + 1), (i, j - 1), (i + 1, j), (i - 1, j)]
        inside = [0 <= a < H and 0 <= b < W and fg[a, b] for a, b in near]
        right, left, down, up = (point(a, b) if ok else point(i, j) for (a, b), ok in zip(near, inside))
        e, f = [x - y for x, y in zip(right, left)], [x - y for x, y in zip(down, up)]
        n = unit([e[1] * f[2] - e[2] * f[1], e[2] * f[0] - e[0] * f[2], e[0] * f[1] - e[1] * f[0]])
        own[i, j] = n
        if all(ok and tri_id[a, b] == tri_id[i, j] for (a, b), ok in zip(near, inside)):
            acc = sums.setdefault(int(tri_id[i, j]), [0.0, 0.0, 0.0])
            for c in range(3):
                acc[c] += n[c]
    light = unit(list(light))
    out = np.empty((H, W, 3), np.uint8)
    out[...] = bg
    for (i, j), n in own.items():
        n = unit(sums.get(int(tri_id[i, j]), n))
        p = point(i, j)
        if sum(a * b for a, b in zip(n, p)) > 0:
            n = [-c for c in n]
        v = unit([-c for c in p])
        h = unit([a + b for a, b in zip(light, v)])
        diffuse = max(sum(a * b for a, b in zip(n, light)), 0.0)
        spec = specular * max(sum(a * b for a, b in zip(n, h)), 0.0) ** shininess
        base = albedo[min(int(mat_id[i, j]), len(albedo) - 1)]
        out[i, j] = linear_to_srgb8(np.array([c * (ambient + (1 - ambient) * diffuse) + spec
                                              for c in base]))
    return out


def test_stored_view_shading_follows_its_definition_pixel_by_pixel(runtime):
    """``shade_stored_view`` (vectorised over the vehicle's pixels) against its definition
    evaluated pixel by pixel (``_stored_view_by_definition``): a vehicle cut by the image's
    edges, one left alone on a pixel, and face indices spread over 2^32 (the grouping of a
    face's pixels by ``np.unique`` instead of by offset: the same bytes)."""
    mesh = _scene()
    ring = make_ring(60.0, (20.0,), size=40, distance=1.1)     # close: cut by the edges
    views = render_views(mesh, ring, runtime=runtime)
    kw = dict(light=(-0.4, -0.6, -1.0), ambient=0.3, specular=0.25, shininess=32.0)
    albedo = np.array([(0.8, 0.8, 0.8)] + [m.base_color[:3] for m in mesh.materials])
    lone = np.full_like(views.depth[0], np.inf)
    lone[7, 9] = 2.0
    cases = [(views.depth[v], views.mat_id[v], views.tri_id[v]) for v in range(ring.n_views)]
    cases.append((lone, views.mat_id[0], views.tri_id[0]))
    cut = 0
    for depth, mat, tri in cases:
        fg = np.isfinite(depth)
        cut += int(fg[0].any() or fg[-1].any() or fg[:, 0].any() or fg[:, -1].any())
        got = shade_stored_view(depth, mat, tri, ring.K, albedo, light_dir=kw["light"],
                                ambient=kw["ambient"], specular=kw["specular"],
                                shininess=kw["shininess"], background=(9, 8, 7))
        want = _stored_view_by_definition(depth, mat, tri, ring.K, albedo, bg=(9, 8, 7), **kw)
        diff = np.abs(got.astype(int) - want.astype(int))
        assert diff.max() <= 1 and np.mean(diff.max(-1)[fg] == 0) > 0.98   # float sums' order
        spread = np.where(fg, tri.astype(np.uint64) * 65521 % (2**32 - 1), tri).astype(np.uint32)
        assert np.array_equal(shade_stored_view(depth, mat, spread, ring.K, albedo,
                                                light_dir=kw["light"], background=(9, 8, 7)),
                              got)
    assert cut >= 2                                       # the edges are exercised
    empty = shade_stored_view(np.zeros((0, 5), np.float32), np.zeros((0, 5), np.uint16),
                              np.zeros((0, 5), np.uint32), ring.K, albedo)
    assert empty.shape == (0, 5, 3)


def test_two_sided_winding_does_not_matter(runtime):
    mesh = _scene()
    flipped = Mesh(**{**mesh.__dict__, "faces": mesh.faces[:, ::-1].copy()})
    ring = make_ring(90.0, (30.0,), size=48)
    a = shade_views(mesh, render_views(mesh, ring), runtime=runtime)
    b = shade_views(flipped, render_views(flipped, ring), runtime=runtime)
    assert np.array_equal(a, b)
    assert a.max() > 0


def test_colors_override_and_background_image(runtime):
    mesh = _scene()
    ring = make_ring(180.0, (10.0,), size=32)
    views = render_views(mesh, ring, runtime=runtime)
    bg = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    white = shade_views(mesh, views, colors=np.ones((2, 3)), ambient=1.0, specular=0.0,
                        background=bg, runtime=runtime)
    fg = views.tri_id != 0xFFFFFFFF
    assert (white[fg] == 255).all()                               # ambient 1: albedo exactly
    assert np.array_equal(white[~fg], np.broadcast_to(bg, white.shape)[~fg])


def test_bad_arguments_name_the_problem(runtime):
    mesh = _scene()
    views = render_views(mesh, make_ring(180.0, (10.0,), size=16), runtime=runtime)
    with pytest.raises(ValueError, match="colors must be"):
        shade_views(mesh, views, colors=np.ones((1, 3)), runtime=runtime)
    with pytest.raises(ValueError, match="background must be"):
        shade_views(mesh, views, background=np.zeros((8, 8, 3), np.uint8), runtime=runtime)
    with pytest.raises(ValueError, match="light_dir"):
        shade_views(mesh, views, light_dir=(0, 0, 0), runtime=runtime)
    with pytest.raises(ValueError, match="ambient"):
        shade_views(mesh, views, ambient=2.0, runtime=runtime)


def test_device_shading_matches_numpy_reference(runtime):
    """ucad_cl/kernels/shade.cl against the float64 NumPy path: every channel within one 8-bit level."""
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views
    from ucad_cl.shade import shade_views
    from ucad_cl.synth import make_vehicle

    mesh = make_vehicle(4, "suv").mesh()
    views = render_views(mesh, make_ring(azimuth_step=45, elevations=(10.0, 50.0), size=(96, 80)), runtime=runtime)
    for kw in ({}, {"background": (10, 200, 30), "specular": 0.6, "shininess": 8.0},
               {"specular": 0.8, "shininess": 12.5}, {"specular": 0.9, "shininess": 1.0},
               {"background": np.random.default_rng(0).integers(0, 255, (80, 96, 3), np.uint8)}):
        ref = shade_views(mesh, views, device=False, **kw, runtime=runtime).astype(int)
        dev = shade_views(mesh, views, device=True, **kw, runtime=runtime).astype(int)
        assert np.abs(ref - dev).max() <= 1
        assert (ref != dev).mean() < 0.01


@pytest.mark.parametrize("size", [(96, 80), (97, 61)])
def test_vector_and_scalar_shade_kernels_give_identical_bytes(runtime, size):
    """shade_pixels16 (16 pixels a work-item, CPUs) and shade_pixels (one, GPUs) give the same
    bytes: integer shininess of every parity, several lights and backgrounds, an empty view. At
    97 x 61 (not a multiple of 16 pixels) and for a non-integer shininess both run shade_pixels."""
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views
    from ucad_cl.synth import make_vehicle

    mesh = make_vehicle(4, "suv").mesh()
    ring = make_ring(azimuth_step=45, elevations=(10.0, 50.0), size=size)
    views = render_views(mesh, ring, runtime=runtime)
    views.tri_id[0] = 0xFFFFFFFF              # an empty view: every 16-pixel group background
    assert (views.tri_id != 0xFFFFFFFF).any(axis=(1, 2))[1:].all()
    for kw in ({}, {"background": (10, 200, 30), "specular": 0.6, "shininess": 7.0},
               {"specular": 0.9, "shininess": 1.0, "light_dir": (0.5, -0.2, -0.8)},
               {"specular": 0.8, "shininess": 12.5}, {"ambient": 1.0, "specular": 0.0},
               {"background": np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3),
                                                                np.uint8)}):
        a = shade_views(mesh, views, lanes=16, **kw, runtime=runtime)
        b = shade_views(mesh, views, lanes=1, **kw, runtime=runtime)
        assert np.array_equal(a, b), f"{kw}: {int((a != b).any(axis=-1).sum())} pixels differ"
    with pytest.raises(ValueError, match="lanes"):
        shade_views(mesh, views, lanes=8, runtime=runtime)


def test_srgb_bucket_table_is_a_tight_lower_bound():
    """ucad_cl/kernels/shade.cl starts from ``srgb8_bucket_start[int(x * (SRGB_BUCKETS - 1))]``
    and steps up by the exact thresholds: the start must never exceed the level of any float32
    x in the bucket (checked on every float32 next to each bucket boundary and on a dense
    sweep), and stays within a few levels of it (the kernel's loop is short)."""
    from ucad_cl.shade import SRGB_BUCKETS, linear_to_srgb8, srgb8_bucket_start, srgb8_thresholds

    thr = srgb8_thresholds()
    levels = np.arange(1, 256)                      # each threshold the smallest float32 of its level
    assert np.array_equal(linear_to_srgb8(thr.astype(np.float64)), levels)
    assert np.array_equal(linear_to_srgb8(np.nextafter(thr, np.float32(-1)).astype(np.float64)),
                          levels - 1)
    start = srgb8_bucket_start()
    edges = (np.arange(SRGB_BUCKETS) / (SRGB_BUCKETS - 1)).astype(np.float32)
    xs = np.concatenate([np.linspace(0, 1, 2_000_001, dtype=np.float32), edges,
                         np.nextafter(edges, np.float32(-1)), np.nextafter(edges, np.float32(2)),
                         thr, np.nextafter(thr, np.float32(-1))])
    xs = np.clip(xs, 0, 1).astype(np.float32)
    bucket = (xs * np.float32(SRGB_BUCKETS - 1)).astype(np.int32)   # float32 product, truncated
    level = np.searchsorted(thr, xs, side="right")
    assert np.all(start[bucket] <= level)
    assert (level - start[bucket]).max() <= 4
    sample = xs[::997]
    assert np.array_equal(np.searchsorted(thr, sample, side="right"),
                          linear_to_srgb8(sample.astype(np.float64)))


def test_device_shading_is_the_same_whatever_ran_before(runtime):
    """The output buffer is reused across calls (runtime scratch) and the maps are read in place:
    a view set shaded after a larger and a smaller one, or from an unaligned copy of its maps,
    gives the same bytes as shaded first, all within one 8-bit level of the NumPy path."""
    import dataclasses

    from ucad_cl.synth import make_vehicle

    mesh = make_vehicle(6, "sedan").mesh()
    big = render_views(mesh, make_ring(azimuth_step=30, size=64), runtime=runtime)
    small = big.select(np.arange(0, 12, 5))
    first = shade_views(mesh, small, runtime=runtime)
    shade_views(mesh, big, runtime=runtime)
    again = shade_views(mesh, small, runtime=runtime)
    raw = np.empty(small.tri_id.size * 4 + 4, np.uint8)[4:]          # not page- or 8-aligned
    tri = raw[:small.tri_id.size * 4].view(np.uint32).reshape(small.tri_id.shape)
    tri[...] = small.tri_id
    moved = shade_views(mesh, dataclasses.replace(small, tri_id=tri), runtime=runtime)
    assert np.array_equal(first, again) and np.array_equal(first, moved)
    ref = shade_views(mesh, small, device=False).astype(int)
    assert np.abs(ref - first.astype(int)).max() <= 1 and (ref != first).mean() < 0.01
