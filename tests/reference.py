"""Independent references for tests: an exact ray caster (Embree via embreex).

``raycast_views(mesh, ring)`` casts one ray through every pixel centre of every view, starting on
the near plane (so geometry closer than ``ring.near`` is ignored, as the rasterizer clips it), and
returns (V, H, W) triangle ids (int64, -1 = background), material ids (uint16) and depth.
"""
from __future__ import annotations

import numpy as np

from ucad_cl.cameras import pixel_rays


def raycast_views(mesh, ring):
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(mesh.vertices[mesh.faces], dtype=np.float32))
    V, H, W = ring.n_views, ring.height, ring.width
    tri = np.full((V, H, W), -1, np.int64)
    depth = np.full((V, H, W), np.inf, np.float32)
    for v in range(V):
        o, d = pixel_rays(ring.K, ring.w2c[v], W, H)
        d = d.reshape(-1, 3)
        fwd = ring.w2c[v, 2, :3]
        cos = d @ fwd                                  # z_cam per unit of ray length
        start = o[None, :] + d * (ring.near / cos)[:, None]
        res = scene.run(start.astype(np.float32), d.astype(np.float32), output=1)
        ids = np.asarray(res["primID"]).astype(np.int64)
        t = np.asarray(res["tfar"], dtype=np.float64) + ring.near / cos
        hit = ids >= 0
        tri[v].flat[hit.nonzero()[0]] = ids[hit]
        depth[v].flat[hit.nonzero()[0]] = (t * cos)[hit]
    mat = np.where(tri >= 0, mesh.face_material[np.maximum(tri, 0)].astype(np.int64) + 1, 0)
    return tri, mat.astype(np.uint16), depth


def boundary_mask(ids: np.ndarray) -> np.ndarray:
    """(…, H, W) bool: pixels within one pixel (8-neighbourhood) of a change of id."""
    ids = np.asarray(ids)
    pad = np.pad(ids, [(0, 0)] * (ids.ndim - 2) + [(1, 1), (1, 1)], mode="edge")
    H, W = ids.shape[-2:]
    out = np.zeros(ids.shape, bool)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            out |= pad[..., 1 + di:1 + di + H, 1 + dj:1 + dj + W] != ids
    return out


def flat_views(mat_id: np.ndarray):
    """A ViewSet around hand-made material-id maps (identity cameras, no triangles)."""
    from ucad_cl.artifacts import CameraRing, ViewSet

    V, H, W = mat_id.shape
    ring = CameraRing(K=np.eye(3), w2c=np.tile(np.eye(4), (V, 1, 1)), width=W, height=H,
                      azimuth=np.zeros(V), elevation=np.zeros(V), distance=1.0, near=0.01)
    return ViewSet(cameras=ring, tri_id=np.zeros((V, H, W), np.uint32),
                   mat_id=mat_id.astype(np.uint16), depth=np.zeros((V, H, W), np.float32))


def flat_mesh(n_mat: int, sha: str = "ab" * 32):
    """A mesh with ``n_mat`` materials and no faces (classification only needs the maps)."""
    from ucad_cl.artifacts import Material, Mesh

    return Mesh(path="hand-made", sha256=sha, vertices=np.zeros((0, 3)),
                faces=np.zeros((0, 3), np.uint32), face_material=np.zeros(0, np.uint16),
                materials=[Material(name=f"m{i}") for i in range(n_mat)])
