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

Measured (docs/FIT.md, "Ground plates"): it finds the baked-shadow quad of the Toyama sedan
and nothing else in the 44 real models of ``../shared`` or in 200 generated vehicles.
"""
from __future__ import annotations

import numpy as np

PLATE_FLAT = 0.002          # the plate's thickness and the rest's overlap, x the model's diagonal
PLATE_PAST = 0.01           # the plate reaches past the rest's outline by this share, on one side


def ground_plates(vertices: np.ndarray, faces: np.ndarray, face_material: np.ndarray) -> list[int]:
    """Ascending material indices (values of ``face_material``) that are ground plates (module
    doc). ``vertices`` (V, 3) float, ``faces`` (F, 3) int, ``face_material`` (F,) int; faces of
    zero area are ignored for the plane's normal, not for flatness."""
    faces = np.asarray(faces, np.int64)
    face_material = np.asarray(face_material, np.int64)
    mats = np.unique(face_material)
    if mats.size < 2 or len(faces) == 0:
        return []
    v = np.asarray(vertices, np.float64)
    top = float(np.abs(v).max())
    if not 0.0 < top < np.inf:
        return []
    v = v / top                                       # scale-free; the tests below are ratios
    ext = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    tol = PLATE_FLAT * ext
    found = []
    for m in mats:
        own = face_material == m
        f = faces[own]
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        size = np.einsum("ij,ij->i", n, n)
        if not size.max() > 0.0:
            continue
        normal = (n * np.where(n @ n[np.argmax(size)] < 0.0, -1.0, 1.0)[:, None]).sum(axis=0)
        normal /= np.linalg.norm(normal)
        mine = np.unique(f)
        d = v[mine] @ normal
        if d.max() - d.min() > tol:
            continue                                  # not flat
        used = np.zeros(len(v), bool)
        used[faces[~own].ravel()] = True
        used[mine] = False
        rest = v[used]
        if not len(rest):
            continue
        h = rest @ normal - d.mean()
        if h.min() < -tol and h.max() > tol:
            continue                                  # the rest lies on both sides
        if _spans(rest, v[mine], normal):
            found.append(int(m))
    return found


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
