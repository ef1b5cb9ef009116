"""Camera conventions (docs/CONVENTIONS.md) checked numerically."""
import numpy as np
import pytest

from ucad_cl.cameras import (camera_position, label_ring, look_at_many, look_at_w2c, make_ring,
                             pixel_rays)


def project(ring, v, X):
    x = ring.w2c[v, :3, :3] @ X + ring.w2c[v, :3, 3]
    p = ring.K @ x
    return p[:2] / p[2], x[2]


def test_azimuth_and_elevation_conventions():
    assert np.allclose(camera_position(0, 0, 2), [2, 0, 0])
    assert np.allclose(camera_position(90, 0, 2), [0, 0, -2])      # counter-clockwise seen from +Y
    assert np.allclose(camera_position(0, 90 - 1e-9, 2), [0, 2, 0], atol=1e-6)
    ring = make_ring(azimuth_step=90, elevations=(0.0, 30.0), size=(64, 48))
    assert ring.n_views == 8 and list(ring.azimuth[:4]) == [0, 90, 180, 270]
    assert list(ring.elevation) == [0.0] * 4 + [30.0] * 4              # elevation-major
    assert label_ring(ring) == slice(0, 4)                             # the first ring labels
    assert label_ring(make_ring(azimuth_step=45, elevations=(15.0,))) == slice(0, 8)
    for v in range(8):
        R = ring.w2c[v, :3, :3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        (u, w), z = project(ring, v, np.zeros(3))
        assert np.allclose([u, w], [32, 24]) and np.isclose(z, ring.distance)
        # +Y (up) appears above the centre: smaller row coordinate
        assert project(ring, v, np.array([0, 0.1, 0]))[0][1] < 24


def test_look_at_of_many_cameras_equals_the_definition_camera_by_camera():
    """``look_at_many`` (one array computation for a ring) against the look-at rule written for
    one camera in plain Python floats: rows right = forward x up, down = forward x right,
    forward toward the target, translation -R c; lengths sqrt((x^2 + y^2) + z^2). Within 1e-15
    (the translation's sums are the matrix product's), and ``look_at_w2c`` the same bits; any
    azimuth (also past +-360), elevations near the poles, a target off the origin."""
    import math

    def cross(u, v):
        return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]

    def unit(u):
        n = math.sqrt((u[0] * u[0] + u[1] * u[1]) + u[2] * u[2])
        return [x / n for x in u]

    rng = np.random.default_rng(5)
    az = np.concatenate([rng.uniform(-720, 720, 200), [0.0, 90.0, 180.0, 270.0, 360.0]])
    el = np.concatenate([rng.uniform(-89.9, 89.9, 200), [89.9, -89.9, 0.0, 45.0, 5.0]])
    for target in ((0.0, 0.0, 0.0), (0.25, -0.5, 1.5)):
        got = look_at_many(az, el, 3.7, target)
        assert got.shape == (len(az), 4, 4)
        for i, (a, e) in enumerate(zip(az, el)):
            c = [float(p + t) for p, t in zip(camera_position(a, e, 3.7), target)]
            fwd = unit([t - p for t, p in zip(target, c)])
            right = unit(cross(fwd, [0.0, 1.0, 0.0]))
            down = cross(fwd, right)
            R = [right, down, fwd]
            t = [-((R[k][0] * c[0] + R[k][1] * c[1]) + R[k][2] * c[2]) for k in range(3)]
            ref = np.array([R[0] + [t[0]], R[1] + [t[1]], R[2] + [t[2]], [0.0, 0.0, 0.0, 1.0]])
            np.testing.assert_allclose(got[i], ref, rtol=0, atol=1e-15)
            assert np.array_equal(got[i], look_at_w2c(a, e, 3.7, target))
    assert np.array_equal(make_ring(azimuths=az, elevations=[12.5], distance=3.7).w2c,
                          look_at_many(az, np.full(len(az), 12.5), 3.7))


def test_fitted_distance_keeps_the_bounding_sphere_in_frame():
    ring = make_ring(azimuth_step=30, elevations=(-20.0, 10.0, 60.0), size=(96, 64), fov_deg=35)
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(2000, 3))
    pts *= 0.5 / np.linalg.norm(pts, axis=1, keepdims=True)
    for v in range(ring.n_views):
        for X in pts[::50]:
            (u, w), _ = project(ring, v, X)
            assert 0 <= u <= 96 and 0 <= w <= 64


def test_pixel_rays_go_through_pixel_centres():
    ring = make_ring(azimuth_step=120, size=32)
    o, d = pixel_rays(ring.K, ring.w2c[1], 32, 32)
    X = o + 1.7 * d[5, 9]
    (u, w), _ = project(ring, 1, X)
    assert np.allclose([u, w], [9.5, 5.5])


@pytest.mark.parametrize("kwargs", [dict(azimuth_step=7), dict(elevations=(90.0,)), dict(size=0),
                                    dict(fov_deg=180), dict(elevations=())])
def test_bad_rings_are_rejected(kwargs):
    with pytest.raises(ValueError):
        make_ring(**kwargs)


def test_viewset_select_keeps_maps_and_cameras_together():
    from ucad_cl.artifacts import ViewSet

    ring = make_ring(azimuth_step=90, elevations=(0.0, 30.0), size=8)
    V = ring.n_views
    vs = ViewSet(ring, np.arange(V * 64, dtype=np.uint32).reshape(V, 8, 8),
                 np.zeros((V, 8, 8), np.uint16), np.ones((V, 8, 8), np.float32))
    sub = vs.select(np.array([1, 6]))
    assert sub.n_views == sub.cameras.n_views == 2
    assert np.array_equal(sub.tri_id, vs.tri_id[[1, 6]])
    assert np.array_equal(sub.cameras.w2c, ring.w2c[[1, 6]])
    assert list(sub.cameras.azimuth) == [90.0, 180.0] and list(sub.cameras.elevation) == [0.0, 30.0]


def test_single_camera_is_the_rings_view_and_its_distance_the_centres():
    """A one-view ring of a ring's camera equals that view (K, w2c, distance, near) and a
    moved camera's distance is its centre's, found by solving w2c [c; 1] = [0; 0; 0; 1]."""
    from ucad_cl.cameras import NEAR_FRACTION, camera_distance, single_camera

    ring = make_ring(azimuths=[35.0], elevations=[12.0], size=(48, 32), distance=2.5)
    one = single_camera(ring.K, ring.w2c[0], 48, 32, azimuth=35.0, elevation=12.0)
    assert np.array_equal(one.K, ring.K) and np.array_equal(one.w2c, ring.w2c)
    assert (one.width, one.height) == (48, 32)
    assert one.distance == pytest.approx(2.5, abs=1e-12)
    assert one.near == pytest.approx(ring.near, abs=1e-12) == NEAR_FRACTION * 2.5
    w2c = ring.w2c[0].copy()
    w2c[:3, 3] += [0.3, -0.2, 0.9]                         # the camera moved off the ring
    centre = np.linalg.solve(w2c, [0.0, 0.0, 0.0, 1.0])
    assert camera_distance(w2c) == pytest.approx(np.linalg.norm(centre[:3] / centre[3]), rel=1e-12)
    assert single_camera(ring.K, w2c, 48, 32).near == pytest.approx(
        NEAR_FRACTION * camera_distance(w2c), rel=1e-12)
