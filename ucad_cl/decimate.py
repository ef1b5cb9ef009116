"""Decimation to a triangle budget that keeps material boundaries exact (pymeshlab QEM).

``decimate(mesh, budget)`` returns a new :class:`~ucad_cl.artifacts.Mesh` with at most ``budget``
triangles in the same canonical frame (units unchanged; ``file_to_norm``, ``sha256``, ``path``,
``materials`` and ``node_names`` copied; ``face_material`` / ``face_node`` carried per face;
``report.notes`` gets ``"decimated F->F'"``).

Method (``preserve_boundaries=True``, one pymeshlab call on the whole mesh, no split and merge):

1. Weld: vertices with bit-identical coordinates are merged (first occurrence keeps its place).
   CAD files store every material as its own shell, so two materials that meet share positions
   but not vertices; after welding their common border is a set of shared vertices.
2. Lock: a vertex used by faces of two or more materials is locked. Every face touching a locked
   vertex is deselected and the quadric edge collapse (``meshing_decimation_quadric_edge_collapse``,
   ``selected=True``) runs on the selected faces only. MeshLab marks a vertex writable only when
   all its faces are selected and never collapses an edge with a non-writable end, so (by
   construction, checked in the tests): every deselected face survives with bit-identical
   vertices, every material-boundary edge is kept exactly, and every collapse happens inside one
   material, so no face changes material.
3. Every material keeps >= 1 face: for a material with no locked face, its lowest-index face is
   locked (tie rule: lowest face index).
4. Target: MeshLab's ``targetfacenum`` counts selected faces, so it is ``budget - locked``. When
   the locked band takes more than half the budget (measured: a 200k synth vehicle at 5k has a
   4.3k-face band; locked, the rest collapses to 0.7k faces and 72 % of the material-map pixels
   change), an unlocked pass (step 3 still applies) is run instead and ``report.notes`` says
   "boundaries may have moved".

``preserve_boundaries=False`` is plain QEM on the mesh as stored (no weld, no lock; step 3 kept).

Output: faces keep their relative input order, vertices are the welded, still-referenced ones in
first-occurrence order. Face count: exactly ``budget`` or ``budget - 1`` (a collapse removes two
faces; QEM can also stop earlier on tiny meshes); never more unless the note says "budget not
reached". ``budget >= n_faces`` returns the input object itself; a budget below the number of
materials in use raises ``ValueError``. Deterministic: pymeshlab's QEM is single-threaded with a
deterministic heap, so the same input gives bit-identical arrays (tested).

QEM parameters (``QEM_PARAMS``): ``preservenormal`` (no flipped faces), ``planarquadric`` (better
shaped triangles on flat panels), ``qualitythr=0.3``, ``optimalplacement``, ``autoclean=False``
(autoclean would drop faces we promised to keep). ``preserveboundary`` (a soft border quadric) is
off: measured, it spends the budget on borders and the material maps get worse (at 20x on a 200k
synth vehicle 82 % pixel agreement instead of 97 %).

Measured (``bench/decimate.py``, 72 views x 256 px, % of material-map pixels that differ from
the full mesh on the union of both foregrounds, synth vehicles, medians of 2-3 runs, 2 shared cores):

    faces   budget  exact %  plain %  exact s  plain s  +RSS MB
    198k    100k    0.21     0.03     2.8      1.7      140
    198k     50k    0.56     0.04     2.4      1.7      140
    198k     20k    1.73     0.12     1.6      1.5      140
    198k     10k    3.33     0.24     1.8      2.1      140
    198k      5k    6.08*    0.51     1.9      1.9      140     (* band > budget/2: unlocked)
    984k    100k    0.95     0.05    10.9     12.5      504
    984k     50k    1.83     0.09    11.4     12.5      502
    984k     20k    4.77     0.27    12.5     11.0      501

Conclusion: with exact boundaries, budget 100k keeps the material maps within 1 % of the full
mesh up to 1M triangles (RECOMMENDED_BUDGET); 50k stays under 2 %. Plain QEM
(``preserve_boundaries=False``) has 10-20x lower pixel error at every budget on these meshes,
because the locked band eats triangles the QEM would spend on curvature (tyres, rims), so it is
the better choice when exact boundary edges are not required (20k: 0.12 %).
Memory: about 0.5 kB per input triangle (1 GB for 2M); time about 11 s per 1M triangles.

``render_proxy(mesh, cells)`` is the other tool, for speed rather than fidelity: vertex clustering
(Rossignac & Borrel) into a stand-in for renders at low resolution (the fit's pose search of a
heavy mesh, ``fit.POSE_PROXY_FROM``). Each vertex is moved onto the lowest-index vertex of its cell
of a grid of cubes of side ``d / cells`` (``d`` the bounding-box diagonal, the grid anchored at
the box's minimum corner), so no vertex moves more than ``sqrt(3) d / cells`` and every proxy
vertex is an input vertex; faces with two corners in one cell are dropped, the others keep their
order, material and node; vertices are compacted in input order. O(N log N) NumPy, no QEM: 40 ms
for the Ferrari 458's 358,704 triangles (-> 123,871 at 256 cells), 50 ms for a 1M-triangle
generated vehicle (-> 186k). Material boundaries and thin parts may move or vanish: a proxy is
for silhouettes and shading at a few hundred pixels, never stored.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .artifacts import Mesh

#: default triangle budget suggested for the build (chosen from bench/decimate.py, see there)
RECOMMENDED_BUDGET = 100_000

QEM_PARAMS = dict(qualitythr=0.3, preserveboundary=False, preservenormal=True,
                  preservetopology=False, optimalplacement=True, planarquadric=True,
                  planarweight=0.001, qualityweight=False, autoclean=False)


def decimate(mesh: Mesh, budget: int, *, preserve_boundaries: bool = True) -> Mesh:
    """Reduce ``mesh`` to at most ``budget`` triangles, keeping material-boundary edges exact."""
    budget = _validate(mesh, budget)
    n_in = mesh.n_faces
    if budget >= n_in:
        return mesh
    fmat = np.asarray(mesh.face_material)
    V = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    F = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    notes = []
    src = np.arange(n_in)
    if preserve_boundaries:
        V, F = _weld(V, F)
        V, F, src = _collapse(V, F, fmat, budget, lock_materials=True)
        if len(F) > budget:
            notes.append("locked boundary band exceeds half the budget: unlocked pass, "
                         "boundaries may have moved")
    if len(F) > budget:
        V, F, src2 = _collapse(V, F, fmat[src], budget, lock_materials=False)
        src = src[src2]
    if len(F) > budget:
        notes.append(f"budget {budget} not reached")
    V, F = _compact(V, F)
    report = dataclasses.replace(mesh.report, notes=list(mesh.report.notes) +
                                 [f"decimated {n_in}->{len(F)}"] + notes)
    return dataclasses.replace(
        mesh, vertices=V, faces=F.astype(np.uint32), face_material=fmat[src].copy(),
        face_node=None if mesh.face_node is None else np.asarray(mesh.face_node)[src].copy(),
        file_to_norm=np.array(mesh.file_to_norm, copy=True), materials=list(mesh.materials),
        node_names=list(mesh.node_names), report=report)


def render_proxy(mesh: Mesh, cells: int) -> Mesh:
    """``mesh`` clustered on a grid of ``cells`` cubes along its bounding-box diagonal (module
    docstring): vertices move at most ``sqrt(3) / cells`` of the diagonal. Returns ``mesh``
    itself when nothing would be dropped (or everything would)."""
    if isinstance(cells, bool) or not isinstance(cells, (int, np.integer)) or cells < 1:
        raise ValueError(f"cells must be a positive int, got {cells!r}")
    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.faces, np.int64)
    lo = V.min(axis=0)
    side = float(np.linalg.norm(V.max(axis=0) - lo)) / cells
    if not side > 0.0:
        return mesh
    n = cells + 1                                   # cell coordinates 0..cells (the far corner)
    q = np.minimum(np.floor((V - lo) / side), cells).astype(np.int64)
    _, first, inv = np.unique((q[:, 0] * n + q[:, 1]) * n + q[:, 2], return_index=True,
                              return_inverse=True)
    G = first[inv.ravel()][F]                       # each corner -> its cell's first vertex
    keep = (G[:, 0] != G[:, 1]) & (G[:, 1] != G[:, 2]) & (G[:, 0] != G[:, 2])
    if keep.all() or not keep.any():
        return mesh
    V2, F2 = _compact(V, G[keep])
    return dataclasses.replace(
        mesh, vertices=V2, faces=F2.astype(np.uint32),
        face_material=np.asarray(mesh.face_material)[keep],
        face_node=None if mesh.face_node is None else np.asarray(mesh.face_node)[keep])


# ----------------------------------------------------------------------------- helpers

def _validate(mesh: Mesh, budget) -> int:
    if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)):
        raise TypeError(f"budget must be an int, got {type(budget).__name__}")
    budget = int(budget)
    F, V = np.asarray(mesh.faces), np.asarray(mesh.vertices)
    if F.ndim != 2 or F.shape[1] != 3 or V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"mesh {mesh.path}: faces must be (F, 3) and vertices (N, 3), got "
                         f"{F.shape} and {V.shape}")
    if len(F) == 0:
        raise ValueError(f"mesh {mesh.path}: has no faces")
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"mesh {mesh.path}: face index out of range 0..{len(V) - 1}")
    if np.asarray(mesh.face_material).shape != (len(F),):
        raise ValueError(f"mesh {mesh.path}: face_material must have one entry per face")
    if mesh.face_node is not None and np.asarray(mesh.face_node).shape != (len(F),):
        raise ValueError(f"mesh {mesh.path}: face_node must have one entry per face")
    if not np.all(np.isfinite(V)):
        raise ValueError(f"mesh {mesh.path}: non-finite vertex coordinates")
    used = int(np.unique(mesh.face_material).size)
    if budget < used:
        raise ValueError(f"mesh {mesh.path}: budget {budget} is below the number of materials "
                         f"in use ({used}); every material must keep at least one face")
    return budget


def _weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with bit-identical coordinates; the first occurrence keeps its place."""
    _, first, inv = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")          # unique rows in first-occurrence order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return vertices[first[order]], rank[inv.reshape(-1)][faces]


def material_boundary_vertices(faces: np.ndarray, face_material: np.ndarray,
                               n_vertices: int) -> np.ndarray:
    """(N,) bool: vertices used by faces of two or more materials."""
    m = np.repeat(np.asarray(face_material, dtype=np.int64), 3)
    lo = np.full(n_vertices, np.iinfo(np.int64).max)
    hi = np.full(n_vertices, -1, dtype=np.int64)
    idx = np.asarray(faces, dtype=np.int64).ravel()
    np.minimum.at(lo, idx, m)
    np.maximum.at(hi, idx, m)
    return (hi >= 0) & (lo != hi)


def _free_faces(faces: np.ndarray, fmat: np.ndarray, lock: np.ndarray) -> np.ndarray:
    """(F,) bool: faces QEM may change. Each material keeps its lowest-index face if none is locked."""
    free = ~lock[faces].any(axis=1)
    mats, first = np.unique(fmat, return_index=True)        # first face of every material
    has_locked = np.zeros(int(mats.max()) + 1, bool)
    has_locked[fmat[~free]] = True
    free[first[~has_locked[mats]]] = False
    return free


def _collapse(vertices: np.ndarray, faces: np.ndarray, fmat: np.ndarray, budget: int, *,
              lock_materials: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One QEM pass keeping the locked faces. Returns (vertices, faces, source face per face).

    MeshLab's target with ``selected=True`` counts the selected faces only, so the target is the
    budget minus the locked faces; when they alone fill the budget the pass does nothing.
    """
    import pymeshlab

    if lock_materials:
        lock = material_boundary_vertices(faces, fmat, len(vertices))
    else:
        lock = np.zeros(len(vertices), bool)
    free = _free_faces(faces, fmat, lock)
    target = budget - int(np.count_nonzero(~free))
    if target <= budget // 2 and lock_materials:    # the band would starve everything else
        return vertices, faces, np.arange(len(faces))
    if target <= 0:
        return vertices, faces, np.arange(len(faces))
    # face quality (a double) carries the source face index, -(i + 1) for locked faces
    idx = np.arange(len(faces), dtype=np.float64)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=faces.astype(np.int32),
                               f_scalar_array=np.where(free, idx, -(idx + 1.0))))
    ms.compute_selection_by_condition_per_face(condselect="fq >= 0")
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=target, selected=True, **QEM_PARAMS)
    out = ms.current_mesh()
    fq = out.face_scalar_array()
    src = np.where(fq >= 0, fq, -fq - 1.0).astype(np.int64)
    return out.vertex_matrix(), out.face_matrix().astype(np.int64), src


def _compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop unreferenced vertices, keeping the order of the others."""
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return np.ascontiguousarray(vertices[used]), remap[faces]
