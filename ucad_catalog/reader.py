"""``CatalogReader``: the light, read-only view of a catalogue for consumers without OpenCL.

Opens ``ROOT/catalog.sqlite`` with a read-only URI (``mode=ro``); safe while the build's writer
runs (WAL). Each call reads its own snapshot; wrap several calls in ``with reader.snapshot():``
to see one consistent state. Conventions (camera, ids, degrees) are those of ``ucad_cl.artifacts``.

View stacks come from the ``'views.exr'`` artifact (``ucad_catalog.exr``) or, when a mesh has
none, a ``'views.npz'`` artifact with arrays ``tri_id``, ``mat_id``, ``depth`` of shape (V, H, W).
Part masks are derived: mask[part] = mat_id in {index + 1 of the materials labelled ``part``}.
"""
from __future__ import annotations

import contextlib
import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np

from ._db import (CatalogError, check_catalog_db, locate_db, mesh_records, object_path,
                  orientation_column)


@dataclass
class MeshInfo:
    """One catalogued mesh. ``id`` is the mesh rowid (commit order, used to break ties)."""

    id: int
    sha256: str
    path: str
    size: int
    mtime: float
    state: str
    reason: str
    detail: str
    n_triangles: int
    n_materials: int
    file_to_norm: np.ndarray
    options_hash: str
    run_id: int
    timings: dict
    orientation: dict = field(default_factory=dict)   # see ucad_cl.artifacts.Orientation


class PartRow(NamedTuple):
    """Material -> part decision, unpacks as (name, part, score, iou, view, decision, ...)."""

    name: str
    part: str
    score: float
    iou: float
    view: int
    decision: str
    pixels: int
    index: int
    props: dict


@dataclass
class ViewRecord:
    """One view: cameras (K 3x3, w2c 4x4 float64) and maps (H, W): mat_id uint16, tri_id uint32,
    depth float32; part_masks: {part: (H, W) bool} for every part in the mesh's table."""

    sha256: str
    view: int
    K: np.ndarray
    w2c: np.ndarray
    azimuth: float
    elevation: float
    mat_id: np.ndarray
    tri_id: np.ndarray
    depth: np.ndarray
    part_masks: dict[str, np.ndarray] = field(default_factory=dict)
    stats: dict = field(default_factory=dict)


_STATES = ("accepted", "rejected", None)


class CatalogReader:
    """Read-only access to the catalogue directory ``path``."""

    def __init__(self, path: str | Path):
        self.root, db = locate_db(path)
        uri = f"{db.resolve().as_uri()}?mode=ro"
        try:
            self._conn = sqlite3.connect(uri, uri=True, isolation_level=None, timeout=30.0)
        except sqlite3.Error as exc:
            raise CatalogError(f"cannot open catalogue {db}: {exc}") from None
        try:
            check_catalog_db(self._conn, db)
        except CatalogError:
            self._conn.close()
            raise
        self._stack: tuple[str, dict] | None = None       # last view stack read (sha, arrays)
        self._feats: dict[str, np.ndarray] = {}            # features by artifact sha

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> "CatalogReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextlib.contextmanager
    def snapshot(self) -> Iterator["CatalogReader"]:
        """All reads inside the block see the same committed state."""
        self._conn.execute("BEGIN")
        try:
            yield self
        finally:
            self._conn.execute("COMMIT")

    # ------------------------------------------------------------------ index
    def meshes(self, state: str | None = "accepted") -> list[MeshInfo]:
        """Meshes in commit order; ``state`` 'accepted', 'rejected' or None for all."""
        if state not in _STATES:
            raise CatalogError(f"state must be 'accepted', 'rejected' or None, got {state!r}")
        return self._query_meshes("WHERE state=?" if state else "", (state,) if state else ())

    def mesh(self, sha: str) -> MeshInfo:
        """One mesh by content sha256 (any state)."""
        found = self._query_meshes("WHERE sha256=?", (sha,))
        if not found:
            raise CatalogError(f"{self.root}: no mesh with sha256 {sha!r}")
        return found[0]

    def parts(self, sha: str) -> list[PartRow]:
        """Material decisions of mesh ``sha`` ordered by material index."""
        mid = self._mesh_id(sha)
        return [PartRow(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], json.loads(r[8]))
                for r in self._conn.execute(
                    "SELECT name, part, score, iou, view, decision, pixels, idx, props "
                    "FROM materials WHERE mesh_id=? ORDER BY idx", (mid,))]

    def record(self, sha: str) -> dict:
        """The full plain record of one mesh (the jsonl export format)."""
        return mesh_records(self._conn, "WHERE id=?", (self._mesh_id(sha),))[0]

    def artifact_path(self, sha: str, kind: str) -> Path:
        """Path of the object holding artifact ``kind`` of mesh ``sha`` (checked to exist)."""
        mid = self._mesh_id(sha)
        row = self._conn.execute("SELECT sha256 FROM artifacts WHERE mesh_id=? AND kind=?",
                                 (mid, kind)).fetchone()
        if row is None:
            kinds = [r[0] for r in self._conn.execute(
                "SELECT kind FROM artifacts WHERE mesh_id=? ORDER BY kind", (mid,))]
            raise CatalogError(f"mesh {sha[:12]} has no artifact {kind!r} (has {kinds})")
        p = object_path(self.root, row[0])
        if not p.is_file():
            raise CatalogError(f"{self.root}: object {row[0]} ({kind!r} of mesh {sha[:12]}) "
                               "is missing from the object store")
        return p

    # ------------------------------------------------------------------ arrays
    def view(self, sha: str, index: int) -> ViewRecord:
        """Cameras, maps and part masks of view ``index`` of mesh ``sha``."""
        mid = self._mesh_id(sha)
        row = self._conn.execute("SELECT azimuth, elevation, K, w2c, stats FROM views "
                                 "WHERE mesh_id=? AND view=?", (mid, int(index))).fetchone()
        if row is None:
            n = self._conn.execute("SELECT count(*) FROM views WHERE mesh_id=?",
                                   (mid,)).fetchone()[0]
            raise CatalogError(f"mesh {sha[:12]} has no view {index} ({n} views)")
        stack = self._view_stack(sha)
        if not 0 <= index < stack["mat_id"].shape[0]:
            raise CatalogError(f"mesh {sha[:12]}: view {index} is outside its view stack "
                               f"({stack['mat_id'].shape[0]} views)")
        mat_id = stack["mat_id"][index]
        masks: dict[str, list[int]] = {}
        for p in self.parts(sha):
            masks.setdefault(p.part, []).append(p.index + 1)
        return ViewRecord(sha, int(index), np.array(json.loads(row[2]), np.float64),
                          np.array(json.loads(row[3]), np.float64), row[0], row[1],
                          mat_id, stack["tri_id"][index], stack["depth"][index],
                          {part: np.isin(mat_id, ids) for part, ids in sorted(masks.items())},
                          json.loads(row[4]))

    def features(self, sha: str) -> np.ndarray:
        """(V, D) pose features of mesh ``sha`` (the ``'features.npy'`` artifact)."""
        path = self.artifact_path(sha, "features.npy")
        key = path.name
        if key not in self._feats:
            arr = np.load(path, allow_pickle=False)
            if arr.ndim != 2:
                raise CatalogError(f"mesh {sha[:12]}: features.npy has shape {arr.shape}, "
                                   "expected (V, D)")
            self._feats[key] = arr
        return self._feats[key]

    def nearest_views(self, feature: np.ndarray, k: int,
                      sha: str | None = None) -> list[tuple[str, int, float]]:
        """The ``k`` views closest to ``feature`` (D,) by exact squared L2 distance (float64,
        sum of squared differences) over accepted meshes with features, or mesh ``sha`` only.
        Ties: lower (mesh rowid, view) first. Returns [(sha, view, sq_dist)]."""
        q = np.asarray(feature)
        if q.ndim != 1 or not np.issubdtype(q.dtype, np.number) or not np.all(np.isfinite(q)):
            raise CatalogError(f"feature must be a finite numeric (D,) vector, got shape "
                               f"{q.shape}")
        if int(k) < 1:
            raise CatalogError(f"k must be >= 1, got {k}")
        if sha is not None:
            owners = [(self._mesh_id(sha), sha)]
        else:
            owners = self._conn.execute(
                "SELECT m.id, m.sha256 FROM meshes m JOIN artifacts a ON a.mesh_id=m.id "
                "WHERE m.state='accepted' AND a.kind='features.npy' ORDER BY m.id").fetchall()
        if not owners:
            return []
        blocks, mesh_ids, views, shas = [], [], [], []
        for mid, s in owners:
            f = self.features(s)
            if f.shape[1] != q.shape[0]:
                raise CatalogError(f"feature has D={q.shape[0]} but mesh {s[:12]} has "
                                   f"D={f.shape[1]}")
            blocks.append(f)
            mesh_ids.append(np.full(f.shape[0], mid, np.int64))
            views.append(np.arange(f.shape[0], dtype=np.int64))
            shas.extend([s] * f.shape[0])
        diff = np.concatenate(blocks).astype(np.float64) - q.astype(np.float64)
        d = np.einsum("ij,ij->i", diff, diff)
        mesh_id, view = np.concatenate(mesh_ids), np.concatenate(views)
        order = np.lexsort((view, mesh_id, d))[: int(k)]
        return [(shas[i], int(view[i]), float(d[i])) for i in order]

    # ------------------------------------------------------------------ internals
    def _mesh_id(self, sha: str) -> int:
        row = self._conn.execute("SELECT id FROM meshes WHERE sha256=?", (sha,)).fetchone()
        if row is None:
            raise CatalogError(f"{self.root}: no mesh with sha256 {sha!r}")
        return int(row[0])

    def _query_meshes(self, where: str, args: tuple) -> list[MeshInfo]:
        rows = self._conn.execute(
            "SELECT id, sha256, path, size, mtime, state, reason, detail, n_triangles, "
            f"n_materials, file_to_norm, options_hash, run_id, timings, "
            f"{orientation_column(self._conn)} FROM meshes {where} ORDER BY id", args).fetchall()
        return [MeshInfo(*r[:10], np.array(json.loads(r[10]), np.float64), r[11], r[12],
                         json.loads(r[13]), json.loads(r[14])) for r in rows]

    def _view_stack(self, sha: str) -> dict[str, np.ndarray]:
        if self._stack is not None and self._stack[0] == sha:
            return self._stack[1]
        kinds = {r[0] for r in self._conn.execute(
            "SELECT kind FROM artifacts WHERE mesh_id=?", (self._mesh_id(sha),))}
        if "views.exr" in kinds:
            from . import exr                   # the EXR view-stack format (imports no OpenCL)
            try:
                vs, _meta = exr.read_viewset_exr(self.artifact_path(sha, "views.exr"))
            except ValueError as exc:
                raise CatalogError(f"mesh {sha[:12]}: unreadable views.exr: {exc}") from None
            stack = {"tri_id": vs.tri_id, "mat_id": vs.mat_id, "depth": vs.depth}
        elif "views.npz" in kinds:
            with np.load(self.artifact_path(sha, "views.npz"), allow_pickle=False) as z:
                stack = {k: z[k] for k in ("tri_id", "mat_id", "depth")}
        else:
            raise CatalogError(f"mesh {sha[:12]} has no view stack artifact "
                               f"('views.exr' or 'views.npz'; has {sorted(kinds)})")
        self._stack = (sha, stack)
        return stack
