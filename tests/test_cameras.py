"""Camera conventions (docs/CONVENTIONS.md) checked numerically."""
import numpy as np
import pytest

from ucad_cl.cameras import camera_position, label_ring, make_ring, pixel_rays


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
