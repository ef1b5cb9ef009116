"""UrbanCAD's CAD model filter: keep models whose materials can name their parts.

Two checks, each returning a :class:`~ucad_cl.artifacts.Verdict` whose ``reason`` is a short code
(empty when accepted) and whose ``detail`` is a sentence with the numbers behind the decision.

``filter_mesh`` looks at geometry only, checks in this order (the first failing one is reported):

* ``empty``               no faces or no vertices;
* ``non_finite``          a NaN/inf vertex coordinate;
* ``too_many_triangles``  more than ``max_triangles`` faces (default 2,000,000);
* ``too_few_materials``   fewer than ``min_materials`` (default 2) distinct materials used by faces.

``filter_views`` looks at rendered material-id maps (``ViewSet.mat_id``, id = material index + 1,
0 = background), counting pixels over all views, in this order:

* ``too_few_visible_parts`` no visible pixel at all;
* ``dominant_material``     one material covers >= ``dominant_fraction`` (default 0.97) of all
  visible pixels (ties: the lowest material index is named);
* ``too_few_visible_parts`` fewer than ``min_visible_materials`` (default 2) materials have at
  least ``min_pixels`` (default 20) pixels.

So a model that shows a single material is reported as ``dominant_material``.
"""
from __future__ import annotations

import numpy as np

from .artifacts import Mesh, Verdict, ViewSet


def filter_mesh(mesh: Mesh, *, min_materials: int = 2, max_triangles: int = 2_000_000) -> Verdict:
    """Geometry-level filter: empty, non-finite, too many triangles, too few materials."""
    if min_materials < 1 or max_triangles < 1:
        raise ValueError(f"min_materials and max_triangles must be >= 1, "
                         f"got {min_materials} and {max_triangles}")
    faces = np.asarray(mesh.faces)
    vertices = np.asarray(mesh.vertices)
    face_material = np.asarray(mesh.face_material)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"mesh.faces must have shape (F, 3), got {faces.shape}")
    if face_material.shape != (faces.shape[0],):
        raise ValueError(f"mesh.face_material must have shape ({faces.shape[0]},), "
                         f"got {face_material.shape}")
    if faces.shape[0] == 0 or vertices.size == 0:
        return Verdict(False, "empty", f"mesh has {faces.shape[0]} faces and "
                                       f"{len(vertices)} vertices")
    bad = int((~np.isfinite(vertices)).any(axis=-1).sum())
    if bad:
        return Verdict(False, "non_finite", f"{bad} of {len(vertices)} vertices have NaN/inf "
                                            f"coordinates")
    if faces.shape[0] > max_triangles:
        return Verdict(False, "too_many_triangles", f"{faces.shape[0]} triangles exceed the "
                                                    f"limit of {max_triangles}")
    if face_material.size and int(face_material.max()) >= len(mesh.materials):
        raise ValueError(f"mesh.face_material refers to material {int(face_material.max())} but "
                         f"the mesh has {len(mesh.materials)} materials")
    used = int(np.unique(face_material).size)
    if used < min_materials:
        return Verdict(False, "too_few_materials", f"faces use {used} distinct material(s), "
                                                   f"fewer than the minimum of {min_materials}")
    return Verdict(True, "", f"{faces.shape[0]} triangles, {used} materials used")


def filter_views(mesh: Mesh, views: ViewSet, *, dominant_fraction: float = 0.97,
                 min_visible_materials: int = 2, min_pixels: int = 20) -> Verdict:
    """Render-level filter on material-id maps: one dominant material, too few visible parts."""
    if not 0.0 < dominant_fraction <= 1.0:
        raise ValueError(f"dominant_fraction must be in (0, 1], got {dominant_fraction}")
    if min_visible_materials < 1 or min_pixels < 1:
        raise ValueError(f"min_visible_materials and min_pixels must be >= 1, "
                         f"got {min_visible_materials} and {min_pixels}")
    mat_id = np.asarray(views.mat_id)
    if mat_id.ndim != 3:
        raise ValueError(f"views.mat_id must have shape (V, H, W), got {mat_id.shape}")
    if mat_id.dtype != np.uint16:
        raise ValueError(f"views.mat_id must be uint16, got {mat_id.dtype}")
    n_mat = len(mesh.materials)
    try:
        counts = views.material_counts(n_mat + 1).sum(axis=0)
    except ValueError:
        raise ValueError(f"views.mat_id holds material id {int(mat_id.max())} but the mesh has "
                         f"{n_mat} materials (ids 1..{n_mat})") from None
    visible = counts[1:]
    total = int(visible.sum())
    if total == 0:
        return Verdict(False, "too_few_visible_parts",
                       f"no material is visible in {mat_id.shape[0]} views")
    top = int(np.argmax(visible))                    # first maximum = lowest material index
    fraction = visible[top] / total
    if fraction >= dominant_fraction:
        return Verdict(False, "dominant_material",
                       f"material {top} ({mesh.materials[top].name!r}) covers {fraction:.4f} of "
                       f"{total} visible pixels (limit {dominant_fraction})")
    seen = int((visible >= min_pixels).sum())
    if seen < min_visible_materials:
        return Verdict(False, "too_few_visible_parts",
                       f"{seen} material(s) have >= {min_pixels} visible pixels, fewer than "
                       f"{min_visible_materials}")
    return Verdict(True, "", f"{seen} materials visible with >= {min_pixels} pixels; largest "
                             f"({mesh.materials[top].name!r}) covers {fraction:.4f} of {total} "
                             f"pixels")
