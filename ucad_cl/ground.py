"""Ground plates: a material that is one flat plate spanning the whole model on one side.

Sketchfab-style exports often carry a helper under the vehicle: a baked-shadow quad, a ground
sheet, a display plate. It is not part of the vehicle, yet it is drawn in every view: the
catalogue's silhouettes and features then show a plate that no photo shows (the fit's object mask
never holds it), and it widens the bounding box the canonical frame and the cameras are scaled
by. ``ground_plates`` finds such materials from geometry alone, in any frame (it runs before the
orientation stage); ``ingest.load_mesh`` leaves their faces out, with a note.

A material is a ground plate when all of these hold (``ext``: the model's bounding-box diagonal):

* it is flat: its vertices lie within ``PLATE_FLAT * ext`` of one plane (the plane's normal: its
  faces' normals summed, each turned to agree with its largest face's, so mixed winding does
  not cancel them);
* the plane supports the rest of the model: every other vertex lies on one side of it (within
  the same tolerance);
* it spans the rest: in the rest's principal axes within the plane, the plate's rectangle holds
  the rest's rectangle on every side and reaches past it by at least ``PLATE_PAST`` of the rest's
  extent on one side (a baked shadow or ground sheet is larger than the vehicle; a flat roof or
  floor panel of the vehicle itself never holds all of its outline, and one exactly as large as
  the rest's outline, the lid of a plain box, is not taken);
* the model has another material (a one-material model is never emptied).

Only materials whose bounding box is at least ``PLATE_SIZE`` of the model's diagonal are tested
(a plate that spans the rest is that large), the ``PLATE_CANDIDATES`` largest of them (a real
export has a few such materials; a hostile file of thousands of large triangles, each its own
material, costs one sort and sixteen tests, not one test a material).

Measured (docs/FIT.md, "Ground plates left out at ingest"): it finds the baked-shadow quad of
the Toyama sedan and nothing else in the 44 real models of ``../shared`` or in the 960 generated
vehicles of ``bench/fit.py``'s catalogue. Cost: ~12 ms for the Toyama's 25k faces, ~110 ms for
the 359k of the three.js Ferrari (AMD EPYC Zen 4, one core).
"""
from __future__ import annotations

import numpy as np

PLATE_FLAT = 0.002          # the plate's thickness and the rest's overlap, x the model's diagonal
PLATE_PAST = 0.01           # the plate reaches past the rest's outline by this share, on one side
PLATE_SIZE = 0.5            # only materials this large (box diagonal / the model's) are tested,
PLATE_CANDIDATES = 16       # ... the largest this many of them (each test reads the whole model)
PLATE_SAMPLE = 64           # faces of a material tested for flatness before all of them


def ground_plates(vertices: np.ndarray, faces: np.ndarray, face_material: np.ndarray) -> list[int]:
    """Ascending material indices (values of ``face_material``) that are ground plates (module
    doc). ``vertices`` (V, 3) float, ``faces`` (F, 3) int, ``face_material`` (F,) int; faces of
    zero area are ignored for the plane's normal, not for flatness."""
    faces = np.asarray(faces, np.int64)
    face_material = np.asarray(face_material, np.int64)
    if len(faces) == 0 or face_material.min() == face_material.max():
        return []                                     # one material: never emptied
    v = np.asarray(vertices, np.float64)
    top = float(np.abs(v).max())
    if not 0.0 < top < np.inf:
        return []
    v = v / top                                       # scale-free; the tests below are ratios
    ext = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    tol = PLATE_FLAT * ext
    found = []
    for m in _large_materials(v, faces, face_material, PLATE_SIZE * ext):
        own = face_material == m
        f = faces[own]
        some = f[::max(1, len(f) // PLATE_SAMPLE)]    # a curved part fails on a few faces
        if _flat_plane(v, some, tol) is None:
            continue
        plane = _flat_plane(v, f, tol)
        if plane is None:
            continue
        normal, height = plane
        mine = np.unique(f)
        used = np.zeros(len(v), bool)
        used[faces[~own].ravel()] = True
        used[mine] = False
        rest = v[used]
        if len(rest) < 3:
            continue
        h = rest @ normal - height
        if h.min() < -tol and h.max() > tol:
            continue                                  # the rest lies on both sides
        if _spans(rest, v[mine], normal):
            found.append(int(m))
    return found


def _normal(v: np.ndarray, f: np.ndarray) -> np.ndarray | None:
    """The unit normal of faces ``f``: their normals summed, each turned to agree with the
    largest's (mixed winding does not cancel them); None when every face has zero area."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    size = np.einsum("ij,ij->i", n, n)
    if not size.max() > 0.0:
        return None
    s = (n * np.where(n @ n[np.argmax(size)] < 0.0, -1.0, 1.0)[:, None]).sum(axis=0)
    return s / np.linalg.norm(s)


def _flat_plane(v: np.ndarray, f: np.ndarray, tol: float) -> tuple[np.ndarray, float] | None:
    """(``_normal`` of faces ``f``, the height of the middle of their corners along it) when
    every corner lies within ``tol`` of one plane, else None."""
    normal = _normal(v, f)
    if normal is None:
        return None
    d = v[f] @ normal
    if d.max() - d.min() > tol:
        return None
    return normal, float(d.max() + d.min()) / 2


def _large_materials(v: np.ndarray, faces: np.ndarray, face_material: np.ndarray,
                     size: float) -> list[int]:
    """Ascending materials whose vertices' bounding box has a diagonal of at least ``size``, the
    ``PLATE_CANDIDATES`` largest of them: one pass over the faces grouped by material, so a
    file of thousands of materials costs one sort and at most that many tests of the model."""
    order = np.argsort(face_material, kind="stable")
    mat = face_material[order]
    fo = faces[order]
    a, b, c = (np.take(v, fo[:, k], axis=0) for k in range(3))
    starts = np.flatnonzero(np.r_[True, mat[1:] != mat[:-1]])
    lo = np.minimum.reduceat(np.minimum(np.minimum(a, b), c), starts)
    hi = np.maximum.reduceat(np.maximum(np.maximum(a, b), c), starts)
    diag = np.linalg.norm(hi - lo, axis=1)
    big = np.flatnonzero(diag >= size)
    big = big[np.argsort(-diag[big], kind="stable")][:PLATE_CANDIDATES]   # ties: lower material
    return sorted(int(m) for m in mat[starts][big])


def _spans(rest: np.ndarray, plate: np.ndarray, normal: np.ndarray) -> bool:
    """Whether ``plate``'s points, projected on the plane of ``normal``, hold ``rest``'s in the
    rest's principal axes and reach past them by ``PLATE_PAST`` on at least one side."""
    e1 = np.cross(normal, (1.0, 0.0, 0.0) if abs(normal[0]) < 0.9 else (0.0, 1.0, 0.0))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    axes = np.stack([e1, e2], axis=1)                 # (3, 2): the plane's coordinates
    r, p = rest @ axes, plate @ axes
    _, turn = np.linalg.eigh(np.cov((r - r.mean(axis=0)).T).reshape(2, 2))
    r, p = r @ turn, p @ turn
    lo, hi = r.min(axis=0), r.max(axis=0)
    span = np.maximum(hi - lo, 1e-12)
    below, above = (lo - p.min(axis=0)) / span, (p.max(axis=0) - hi) / span
    margin = PLATE_FLAT * 1e-3
    return bool((below >= -margin).all() and (above >= -margin).all()
                and max(below.max(), above.max()) >= PLATE_PAST)
