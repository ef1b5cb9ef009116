"""``CatalogReader``: the light, read-only view of a catalogue for consumers without OpenCL.

    import ucad_catalog
    cat = ucad_catalog.open("sample-catalog/catalog")
    m = cat.meshes()[0]                       # MeshInfo; m.id is the content sha256
    cat.parts(m.id)                           # material -> part table with properties
    v = cat.view(m.id, azimuth=90, elevation=15)   # the nearest view: maps, cameras, part masks
    cat.edges(m.id, v.view)                   # (H, W) bool Canny edges of that view
    e = cat.entry(m.id[:8])                   # parts, cameras, artifacts, provenance at once

**Mesh ids.** A mesh is named by its id, the sha256 of its source content, or any prefix of at
least ``MIN_ID_PREFIX`` (8) hex digits; ``mesh(key)`` also takes the source path in any spelling
(absolute, relative to the working folder or to the library root, with ``./`` or ``..``) or the
bare file name. A key matching several meshes is a ``CatalogError`` listing them.

**Order.** Listings are ordered by (library root, path, sha256): independent of how a build
scheduled its workers. Ties between equal feature distances go to the lower (sha256, view).

**Reads.** Opens ``ROOT/catalog.sqlite`` read-only (``mode=ro``); safe while a build writes
(WAL). Each call reads its own snapshot; ``with reader.snapshot():`` makes several calls see
one state. A view read decodes only that view's part of the EXR view stack (``exr.ViewStackFile``);
headers of the last few stacks are kept per reader. Part masks are derived: mask[part] =
mat_id in {index + 1 of the materials labelled ``part``}. Edges come from the ``edges.npy.gz``
artifact (packed bits of (V, H, W), ``np.packbits`` along W). Conventions (cameras, ids,
degrees): docs/CONVENTIONS.md and ``ucad_catalog.views``.
"""
from __future__ import annotations

import contextlib
import gzip
import io
import json
import math
import os
import sqlite3
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Iterator, NamedTuple

import numpy as np

from .export import format_for, write_export
from .exr import ViewStackFile
from ._db import (MESH_ORDER, RECENT_RUNS, CatalogError, catalog_status, check_catalog_db,
                  feature_key, feature_objects, locate_db, mesh_records, object_path, run_rows,
                  verify_catalog)
from .searchindex import SearchIndex, load_search_index

MIN_ID_PREFIX = 8          # hex digits of a sha256 prefix accepted as a mesh id
_OPEN_STACKS = 64          # view stacks kept open per reader (headers and offsets, ~50 KB each
                           # at 72 views; an open reads the headers only: ~0.6 ms)


@dataclass
class MeshInfo:
    """One catalogued mesh. ``id`` is its public id, the sha256 of the source content.
    ``path`` is relative to ``library_root`` (absolute when the file was outside it)."""

    sha256: str
    library_root: str
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
    orientation: dict | None = None
    meta: dict = field(default_factory=dict)

    @property
    def id(self) -> str:
        return self.sha256

    @property
    def name(self) -> str:
        return Path(self.path).name

    @property
    def source(self) -> Path:
        """Where the source file was when it was catalogued."""
        return Path(_source(self.library_root, self.path))


def _source(library_root: str, path: str) -> str:
    """A mesh's recorded source path from its catalogue columns (``MeshInfo.source``)."""
    return str(Path(library_root) / path if library_root else Path(path))


class PartRow(NamedTuple):
    """Material -> part decision, unpacks as (name, part, score, iou, view, decision, ...).
    ``props``: the material's recorded properties (base_color, metallic, roughness, ...)."""

    name: str
    part: str
    score: float
    iou: float
    view: int
    decision: str
    pixels: int
    index: int  # type: ignore[assignment]   # the material index (shadows tuple.index)
    props: dict


@dataclass
class ViewInfo:
    """One camera: index, azimuth / elevation (degrees), K (3, 3) and w2c (4, 4) float64."""

    index: int
    azimuth: float
    elevation: float
    K: np.ndarray
    w2c: np.ndarray
    stats: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ViewAngles:
    """One camera's index and azimuth / elevation (degrees): a ``ViewInfo`` without the
    matrices (``CatalogReader.view_angles``)."""

    index: int
    azimuth: float
    elevation: float


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


@dataclass
class MeshEntry:
    """Everything about one mesh in one object: ``info`` (MeshInfo: id, paths, state,
    orientation, meta), ``parts`` (material -> part with properties), ``views`` (cameras),
    ``artifacts`` {kind: object path} and ``provenance``: where the source was (library root,
    path, size, mtime) and what made the row (options hash, the run's options including the code
    version, engine, run start time)."""

    info: MeshInfo
    parts: list[PartRow]
    views: list[ViewInfo]
    artifacts: dict[str, Path]
    provenance: dict

    @property
    def id(self) -> str:
        return self.info.sha256

    @property
    def orientation(self) -> dict | None:
        return self.info.orientation


@dataclass(frozen=True)
class FeatureTable:
    """The stored pose features of every accepted mesh that has readable ones, stacked for a
    catalogue-wide search: ``feats`` (N, D) float32 rows; ``mesh`` (N,) int64, each row's index
    into ``meshes``; ``view`` (N,) int64, its view index. Meshes in ``meshes()`` order (library
    root, path, sha256), each mesh's rows in view order. ``skipped``: (sha256, why) of the
    accepted meshes left out (no ``features.npy``: built with ``--no-features``; or its object
    missing or unreadable). The arrays are read-only: the reader hands the same table to every
    caller."""

    meshes: list[MeshInfo]
    feats: np.ndarray
    mesh: np.ndarray
    view: np.ndarray
    skipped: tuple[tuple[str, str], ...] = ()

    def rows_of(self, k: int) -> np.ndarray:
        """(V, D) rows of ``meshes[k]`` (a read-only view of ``feats``)."""
        lo, hi = np.searchsorted(self.mesh, [k, k + 1])
        return self.feats[lo:hi]

    def rows(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), D) rows by row number (a copy; as ``SearchIndex.rows``)."""
        return self.feats[np.asarray(rows, np.int64)]


_STATES = ("accepted", "rejected", None)
_IN_LIST = 500              # ids in one "IN (...)" query at most (SQLite's limit is 999 or more)
_MESH_COLUMNS = ("sha256, library_root, path, size, mtime, state, reason, detail, n_triangles, "
                 "n_materials, file_to_norm, options_hash, run_id, timings, orientation, meta")


class CatalogReader:
    """Read-only access to the catalogue directory ``path`` (see the module docstring)."""

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
        self._stacks: OrderedDict[str, ViewStackFile] = OrderedDict()   # artifact sha -> ViewStackFile
        self._npz: tuple[str, dict] | None = None                 # last views.npz read
        self._edges: tuple[str, np.ndarray] | None = None         # last edge stack read
        self._feats: dict[str, np.ndarray] = {}                   # features by artifact sha
        self._table: tuple[tuple, FeatureTable] | None = None     # (what it was built from, it)
        self._index: tuple[tuple, tuple[SearchIndex | None, str]] | None = None   # the same

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> "CatalogReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextlib.contextmanager
    def snapshot(self) -> Iterator["CatalogReader"]:
        """All reads inside the block see the same committed state (blocks may nest)."""
        if self._conn.in_transaction:
            yield self
            return
        self._conn.execute("BEGIN")
        try:
            yield self
        finally:
            self._conn.execute("COMMIT")

    # ------------------------------------------------------------------ whole catalogue
    def status(self, recent: int = RECENT_RUNS) -> dict:
        """Counts by state and reason, object totals, the run count and the ``recent`` last runs
        (as ``Catalog.status``; keys in SCHEMA.md, 'Command output'), one snapshot."""
        return catalog_status(self._conn, self.root, recent)

    def verify(self, rehash: bool = True) -> dict:
        """Consistency report (``_db.verify_catalog``): problems, unreferenced objects."""
        return verify_catalog(self._conn, self.root, rehash)

    def runs(self, n: int = RECENT_RUNS) -> list[dict]:
        """The last ``n`` runs, newest first: id, started, finished, engine, options_hash,
        counts, meshes/s (the rows of ``status()["runs"]``)."""
        return run_rows(self._conn, n)

    # ------------------------------------------------------------------ index
    def meshes(self, state: str | None = "accepted") -> list[MeshInfo]:
        """Meshes ordered by (library root, path, sha256); ``state`` 'accepted', 'rejected' or
        None for all."""
        if state not in _STATES:
            raise CatalogError(f"state must be 'accepted', 'rejected' or None, got {state!r}")
        return self._query_meshes("WHERE state=?" if state else "", (state,) if state else ())

    def mesh(self, key: str) -> MeshInfo:
        """The one mesh ``key`` names (id, id prefix, path in any spelling, file name)."""
        hits = self.find(key)
        if not hits:
            raise CatalogError(f"{self.root}: no mesh matches {key!r} (give its id, an id prefix "
                               f"of >= {MIN_ID_PREFIX} hex digits, its path or its file name)")
        if len(hits) > 1:
            listing = ", ".join(f"{m.sha256[:12]} {m.path}" for m in hits[:6])
            raise CatalogError(f"{self.root}: {len(hits)} meshes match {key!r}: {listing}"
                               f"{' ...' if len(hits) > 6 else ''}; give more of the id")
        return hits[0]

    def find(self, key: str) -> list[MeshInfo]:
        """Every mesh ``key`` names; the first rule with a match wins: full id, id prefix
        (>= MIN_ID_PREFIX hex digits), source path (any spelling), file name."""
        key = str(key).strip()
        k = key.lower()
        if _is_hex(k) and len(k) >= MIN_ID_PREFIX:
            hits = self._query_meshes("WHERE sha256 >= ? AND sha256 < ?", (k, k + "g"))
            if hits:
                return hits
        rows = self._conn.execute("SELECT sha256, library_root, path FROM meshes "
                                  f"ORDER BY {MESH_ORDER}").fetchall()   # (match on these alone)
        named = _SameFile(key)
        relative = None if os.path.isabs(key) else _norm(key)
        hits = [sha for sha, root, path in rows
                if named.is_(_source(root, path)) or relative == _norm(path)]
        if not hits:
            hits = [sha for sha, _, path in rows
                    if (name := PurePath(path).name) == key or name.lower() == k]
        if len(hits) > _IN_LIST:
            wanted = set(hits)
            return [m for m in self.meshes(state=None) if m.sha256 in wanted]
        return self._query_meshes(f"WHERE sha256 IN ({', '.join('?' * len(hits))})",
                                  tuple(hits)) if hits else []

    def parts(self, key: str) -> list[PartRow]:
        """Material decisions of a mesh, ordered by material index, with material properties."""
        mid = self._mesh_id(key)
        return [PartRow(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], json.loads(r[8]))
                for r in self._conn.execute(
                    "SELECT name, part, score, iou, view, decision, pixels, idx, props "
                    "FROM materials WHERE mesh_id=? ORDER BY idx", (mid,))]

    def entry(self, key: str) -> MeshEntry:
        """The mesh ``key`` names with its part table, cameras, artifacts and provenance, read in
        one snapshot."""
        with self.snapshot():
            info = self.mesh(key)
            mid = self._mesh_id(info.sha256)
            arts = {k: object_path(self.root, s) for k, s in self._conn.execute(
                "SELECT kind, sha256 FROM artifacts WHERE mesh_id=? ORDER BY kind", (mid,))}
            run = self._conn.execute("SELECT options, engine, started FROM runs WHERE id=?",
                                     (info.run_id,)).fetchone()
            provenance = {"library_root": info.library_root, "path": info.path,
                          "size": info.size, "mtime": info.mtime,
                          "options_hash": info.options_hash, "run_id": info.run_id,
                          "options": json.loads(run[0]) if run else None,
                          "engine": run[1] if run else None,
                          "run_started": run[2] if run else None}
            return MeshEntry(info, self.parts(info.sha256), self.views(info.sha256), arts,
                             provenance)

    def record(self, key: str) -> dict:
        """The full plain record of one mesh (materials, views, artifacts as plain JSON)."""
        return mesh_records(self._conn, "WHERE id=?", (self._mesh_id(key),))[0]

    def records(self, state: str | None = None) -> list[dict]:
        """Full records of every mesh (or of one ``state``), in listing order, one snapshot."""
        if state not in _STATES:
            raise CatalogError(f"state must be 'accepted', 'rejected' or None, got {state!r}")
        return mesh_records(self._conn, "WHERE state=?" if state else "",
                            (state,) if state else ())

    def export(self, out: str | Path, format: str | None = None) -> int:
        """Export the catalogue (meshes table + materials table, ``ucad_catalog.export``)."""

        format_for(out, format)
        with self.snapshot():
            records = self.records()
        return write_export(records, out, format)

    def artifact_path(self, key: str, kind: str) -> Path:
        """Path of the object holding artifact ``kind`` of a mesh (checked to exist)."""
        mid = self._mesh_id(key)
        row = self._conn.execute("SELECT sha256 FROM artifacts WHERE mesh_id=? AND kind=?",
                                 (mid, kind)).fetchone()
        if row is None:
            kinds = [r[0] for r in self._conn.execute(
                "SELECT kind FROM artifacts WHERE mesh_id=? ORDER BY kind", (mid,))]
            raise CatalogError(f"mesh {str(key)[:12]} has no artifact {kind!r} (has {kinds})")
        p = object_path(self.root, row[0])
        if not p.is_file():
            raise CatalogError(f"{self.root}: object {row[0]} ({kind!r} of mesh "
                               f"{str(key)[:12]}) is missing from the object store")
        return p

    # ------------------------------------------------------------------ cameras
    def views(self, key: str) -> list[ViewInfo]:
        """Every view of a mesh: index, azimuth, elevation (degrees), K, w2c."""
        mid = self._mesh_id(key)
        return [ViewInfo(r[0], r[1], r[2], np.array(json.loads(r[3]), np.float64),
                         np.array(json.loads(r[4]), np.float64), json.loads(r[5]))
                for r in self._conn.execute(
                    "SELECT view, azimuth, elevation, K, w2c, stats FROM views WHERE mesh_id=? "
                    "ORDER BY view", (mid,))]

    def view_angles(self, key: str) -> list[ViewAngles]:
        """Every view's index, azimuth and elevation (degrees), in view order: ``views``
        without parsing the cameras' matrices (~0.1 against ~2 ms for 144 views)."""
        return [ViewAngles(*r) for r in self._conn.execute(
            "SELECT view, azimuth, elevation FROM views WHERE mesh_id=? ORDER BY view",
            (self._mesh_id(key),))]

    def nearest_view(self, key: str, azimuth: float | None = None,
                     elevation: float | None = None) -> int:
        """Index of the view closest to (azimuth, elevation) in degrees: the smallest angle
        between viewing directions; with one angle only, the smallest difference in that angle
        (azimuths compared modulo 360). Ties: the lower view index."""
        if azimuth is None and elevation is None:
            raise CatalogError("give an azimuth, an elevation or both (degrees)")
        for name, value in (("azimuth", azimuth), ("elevation", elevation)):
            if value is not None and not math.isfinite(float(value)):
                raise CatalogError(f"{name} must be a finite number of degrees, got {value}")
        rows = self._conn.execute("SELECT view, azimuth, elevation FROM views WHERE mesh_id=? "
                                  "ORDER BY view", (self._mesh_id(key),)).fetchall()
        if not rows:
            raise CatalogError(f"mesh {str(key)[:12]} has no views")
        idx = np.array([r[0] for r in rows])
        az, el = (np.radians([r[1] for r in rows]), np.radians([r[2] for r in rows]))
        if azimuth is not None and elevation is not None:
            a, e = math.radians(float(azimuth)), math.radians(float(elevation))
            cos = np.sin(el) * math.sin(e) + np.cos(el) * math.cos(e) * np.cos(az - a)
            dist = np.arccos(np.clip(cos, -1.0, 1.0))
        elif azimuth is not None:
            d = np.abs((np.degrees(az) - float(azimuth)) % 360.0)
            dist = np.minimum(d, 360.0 - d)
        else:
            dist = np.abs(np.degrees(el) - float(elevation))  # type: ignore[arg-type]
        best = np.flatnonzero(dist <= dist.min() + 1e-9)
        return int(idx[best].min())

    # ------------------------------------------------------------------ arrays
    def view(self, key: str, index: int | None = None, *, azimuth: float | None = None,
             elevation: float | None = None, part_masks: bool = True) -> ViewRecord:
        """Cameras, maps and part masks of one view: by ``index``, or the view nearest to
        ``azimuth`` / ``elevation`` (degrees, ``nearest_view``). Decodes only that view.
        ``part_masks=False`` leaves ``ViewRecord.part_masks`` empty (a caller that needs the
        maps only skips a table query and one comparison per part and pixel)."""
        sha = self._sha(key)
        if index is None:
            index = self.nearest_view(sha, azimuth, elevation)
        elif azimuth is not None or elevation is not None:
            raise CatalogError("give a view index or angles, not both")
        row = self._conn.execute("SELECT azimuth, elevation, K, w2c, stats FROM views "
                                 "WHERE mesh_id=? AND view=?",
                                 (self._mesh_id(sha), int(index))).fetchone()
        if row is None:
            n = self._conn.execute("SELECT count(*) FROM views WHERE mesh_id=?",
                                   (self._mesh_id(sha),)).fetchone()[0]
            raise CatalogError(f"mesh {sha[:12]} has no view {index} ({n} views)")
        maps = self._read_view(sha, int(index))
        return ViewRecord(sha, int(index), np.array(json.loads(row[2]), np.float64),
                          np.array(json.loads(row[3]), np.float64), row[0], row[1],
                          maps["mat"], maps["tri"], maps["Z"],
                          self._masks(sha, maps["mat"]) if part_masks else {},
                          json.loads(row[4]))

    def material_map(self, key: str, index: int) -> np.ndarray:
        """(H, W) uint16 material ids of one view (material index + 1; 0 background)."""
        return self._read_view(self._sha(key), int(index), ("mat",))["mat"]

    def depth(self, key: str, index: int) -> np.ndarray:
        """(H, W) float32 linear camera depth of one view (+inf background)."""
        return self._read_view(self._sha(key), int(index), ("Z",))["Z"]

    def triangle_map(self, key: str, index: int) -> np.ndarray:
        """(H, W) uint32 face indices of one view (0xFFFFFFFF background)."""
        return self._read_view(self._sha(key), int(index), ("tri",))["tri"]

    def part_masks(self, key: str, index: int) -> dict[str, np.ndarray]:
        """{part: (H, W) bool} of one view, for every part in the mesh's table."""
        sha = self._sha(key)
        return self._masks(sha, self.material_map(sha, index))

    def edges(self, key: str, index: int | None = None) -> np.ndarray:
        """Canny edges of the material maps: (H, W) bool for view ``index``, (V, H, W) when
        ``index`` is None (the ``edges.npy.gz`` artifact)."""
        sha = self._sha(key)
        path = self.artifact_path(sha, "edges.npy.gz")
        if self._edges is None or self._edges[0] != path.name:
            try:
                packed = np.load(io.BytesIO(gzip.decompress(path.read_bytes())),
                                 allow_pickle=False)
            except (OSError, ValueError, EOFError) as exc:
                raise CatalogError(f"mesh {sha[:12]}: unreadable edges.npy.gz ({exc})") from None
            self._edges = (path.name, packed)
        packed = self._edges[1]
        width = self._image_width(sha)
        if index is None:
            return np.unpackbits(packed, axis=-1, count=width).astype(bool)
        if not 0 <= int(index) < packed.shape[0]:
            raise CatalogError(f"mesh {sha[:12]} has no edge map {index} (edges are stored "
                               f"for the label ring's {packed.shape[0]} views, the first)")
        return np.unpackbits(packed[int(index)], axis=-1, count=width).astype(bool)

    def features(self, key: str) -> np.ndarray:
        """(V, D) pose features of a mesh (the ``'features.npy'`` artifact)."""
        sha = self._sha(key)
        path = self.artifact_path(sha, "features.npy")
        if path.name not in self._feats:
            arr = np.load(path, allow_pickle=False)
            if arr.ndim != 2:
                raise CatalogError(f"mesh {sha[:12]}: features.npy has shape {arr.shape}, "
                                   "expected (V, D)")
            self._feats[path.name] = arr
        return self._feats[path.name]

    def feature_table(self) -> FeatureTable:
        """Every accepted mesh's pose features in one (N, D) array (``FeatureTable``), read
        straight from the ``features.npy`` objects into it (held once, not also per mesh). The
        reader keeps it and returns the same object while the accepted meshes and their feature
        objects are the same (one query per call checks that), so a batch of searches builds
        it once. CatalogError when a mesh's features are not (V, D) or D differs between meshes
        (a catalogue mixing feature settings)."""
        with self.snapshot():
            key = feature_key(self._conn)           # (mesh, its features object or None)
            if self._table is not None and self._table[0] == key:
                return self._table[1]
            metas = self.meshes()
        self._table = None                          # let the old rows go before reading anew
        by_sha = {m.sha256: m for m in metas}       # key and metas: the accepted meshes, in order
        kept: list[MeshInfo] = []
        heads: list[tuple[Path, tuple[int, ...], bool]] = []    # path, shape, raw float32 rows
        items, skipped = feature_objects(self.root, key)
        for sha, path, shape, raw in items:
            if len(shape) != 2 or (heads and shape[1] != heads[0][1][1]):
                want = f"(V, {heads[0][1][1]})" if heads else "(V, D)"
                raise CatalogError(f"mesh {sha[:12]}: features.npy has shape {shape}, "
                                   f"expected {want} like the other meshes")
            kept.append(by_sha[sha])
            heads.append((path, shape, raw))
        rows = [shape[0] for _, shape, _ in heads]
        feats = np.empty((sum(rows), heads[0][1][1] if heads else 0), np.float32)
        at = 0
        for (path, shape, raw), m in zip(heads, kept):
            block = feats[at:at + shape[0]]
            try:
                if raw:                             # the writer's format: straight into place
                    with open(path, "rb") as f:
                        f.seek(-block.nbytes, os.SEEK_END)
                        if f.readinto(block.data.cast("B")) != block.nbytes:
                            raise EOFError("short read")
                else:
                    block[...] = np.load(path, allow_pickle=False)
            except (OSError, ValueError, EOFError) as exc:
                raise CatalogError(f"mesh {m.sha256[:12]}: features.npy changed while it was "
                                   f"read ({exc})") from None
            at += shape[0]
        table = FeatureTable(
            meshes=kept, feats=feats,
            mesh=np.repeat(np.arange(len(kept), dtype=np.int64), rows),
            view=np.concatenate([np.arange(n, dtype=np.int64) for n in rows]) if rows
            else np.zeros(0, np.int64),
            skipped=tuple(skipped))
        for a in (table.feats, table.mesh, table.view):   # shared by every later call: read-only
            a.flags.writeable = False
        self._table = (key, table)
        return table

    def search_index(self) -> tuple[SearchIndex | None, str]:
        """(the catalogue's search index, '') when it is fresh (``ucad_catalog.searchindex``:
        every accepted mesh's features projected, written by each build), else (None, why: no
        index, stale, unreadable). Kept per reader while the feature key is the same."""
        with self.snapshot():
            key = feature_key(self._conn)
            if self._index is not None and self._index[0] == key:
                return self._index[1]
            metas = self.meshes()
        objects = {m: object_path(self.root, o) for m, o in key if o is not None}
        self._index = (key, load_search_index(self.root, key, metas, objects))
        return self._index[1]

    def nearest_views(self, feature: np.ndarray, k: int,
                      sha: str | None = None) -> list[tuple[str, int, float]]:
        """The ``k`` views closest to ``feature`` (D,) by exact squared L2 distance (float64,
        sum of squared differences) over accepted meshes with features, or mesh ``sha`` only.
        Ties: lower (sha256, view) first. Returns [(sha, view, sq_dist)]."""
        q = np.asarray(feature)
        if q.ndim != 1 or not np.issubdtype(q.dtype, np.number) or not np.all(np.isfinite(q)):
            raise CatalogError(f"feature must be a finite numeric (D,) vector, got shape "
                               f"{q.shape}")
        if int(k) < 1:
            raise CatalogError(f"k must be >= 1, got {k}")
        if sha is not None:
            owners = [self._sha(sha)]
        else:
            owners = [r[0] for r in self._conn.execute(
                "SELECT m.sha256 FROM meshes m JOIN artifacts a ON a.mesh_id=m.id "
                "WHERE m.state='accepted' AND a.kind='features.npy' ORDER BY m.sha256")]
        if not owners:
            return []
        blocks, ranks, views = [], [], []
        for r, s in enumerate(owners):
            f = self.features(s)
            if f.shape[1] != q.shape[0]:
                raise CatalogError(f"feature has D={q.shape[0]} but mesh {s[:12]} has "
                                   f"D={f.shape[1]}")
            blocks.append(f)
            ranks.append(np.full(f.shape[0], r, np.int64))
            views.append(np.arange(f.shape[0], dtype=np.int64))
        diff = np.concatenate(blocks).astype(np.float64) - q.astype(np.float64)
        d = np.einsum("ij,ij->i", diff, diff)
        rank, view = np.concatenate(ranks), np.concatenate(views)
        order = np.lexsort((view, rank, d))[: int(k)]
        return [(owners[rank[i]], int(view[i]), float(d[i])) for i in order]

    # ------------------------------------------------------------------ internals
    def _sha(self, key: str) -> str:
        return self.mesh(key).sha256 if not _is_full_sha(key) else key

    def _mesh_id(self, key: str) -> int:
        sha = self._sha(key)
        row = self._conn.execute("SELECT id FROM meshes WHERE sha256=?", (sha,)).fetchone()
        if row is None:
            raise CatalogError(f"{self.root}: no mesh with sha256 {sha!r}")
        return int(row[0])

    def _query_meshes(self, where: str, args: tuple) -> list[MeshInfo]:
        rows = self._conn.execute(f"SELECT {_MESH_COLUMNS} FROM meshes {where} "
                                  f"ORDER BY {MESH_ORDER}", args).fetchall()
        return [MeshInfo(*r[:10], np.array(json.loads(r[10]), np.float64), r[11], r[12],  # type: ignore[call-arg]
                         json.loads(r[13]), None if r[14] is None else json.loads(r[14]),
                         json.loads(r[15])) for r in rows]

    def _masks(self, sha: str, mat_id: np.ndarray) -> dict[str, np.ndarray]:
        """{part: mat_id in the ids of that part's materials}: one table lookup per pixel
        (material id -> part number), then one comparison per part."""
        rows = self._conn.execute("SELECT idx, part FROM materials WHERE mesh_id=? ORDER BY idx",
                                  (self._mesh_id(sha),)).fetchall()
        names = sorted({part for _, part in rows})
        top = max(int(mat_id.max()) if mat_id.size else 0, max((i for i, _ in rows), default=-1) + 1)
        lut = np.zeros(top + 1, np.uint8)                # 0: background / unknown id
        for idx, part in rows:
            lut[idx + 1] = names.index(part) + 1
        code = lut[mat_id]
        return {part: code == k + 1 for k, part in enumerate(names)}

    def _image_width(self, sha: str) -> int:
        """Width of the views in pixels, from the view stack (its display window or shape)."""
        return int(self._read_view(sha, 0, ("mat",))["mat"].shape[1])

    def _read_view(self, sha: str, index: int,
                   channels=("tri", "mat", "Z")) -> dict[str, np.ndarray]:
        kinds = {r[0] for r in self._conn.execute(
            "SELECT kind FROM artifacts WHERE mesh_id=?", (self._mesh_id(sha),))}
        if "views.exr" in kinds:
            path = self.artifact_path(sha, "views.exr")
            stack = self._stacks.pop(path.name, None)
            try:
                if stack is None:
                    stack = ViewStackFile(path)
                self._stacks[path.name] = stack
                while len(self._stacks) > _OPEN_STACKS:
                    self._stacks.popitem(last=False)
                if not 0 <= index < stack.n_views:
                    raise CatalogError(f"mesh {sha[:12]}: view {index} is outside its view "
                                       f"stack ({stack.n_views} views)")
                return stack.read(index, channels)
            except ValueError as exc:
                raise CatalogError(f"mesh {sha[:12]}: unreadable views.exr: {exc}") from None
        if "views.npz" in kinds:
            path = self.artifact_path(sha, "views.npz")
            if self._npz is None or self._npz[0] != path.name:
                with np.load(path, allow_pickle=False) as z:
                    self._npz = (path.name, {"tri": z["tri_id"], "mat": z["mat_id"],
                                             "Z": z["depth"]})
            arrays = self._npz[1]
            if not 0 <= index < arrays["mat"].shape[0]:
                raise CatalogError(f"mesh {sha[:12]}: view {index} is outside its view stack "
                                   f"({arrays['mat'].shape[0]} views)")
            return {c: arrays[c][index] for c in channels}
        raise CatalogError(f"mesh {sha[:12]} has no view stack artifact "
                           f"('views.exr' or 'views.npz'; has {sorted(kinds)})")


def _is_hex(text: str) -> bool:
    return bool(text) and all(c in "0123456789abcdef" for c in text)


def _is_full_sha(text) -> bool:
    return isinstance(text, str) and len(text) == 64 and _is_hex(text)


def _norm(path: str) -> str:
    return os.path.normpath(path).replace(os.sep, "/")


def _lexical(path: str) -> str:
    """``path`` made absolute (relative to the working folder) and normalised, no disk access."""
    return os.path.normpath(os.path.join(os.getcwd(), os.path.expanduser(path)))


def _resolved(lexical: str) -> str:
    """``lexical`` with symlinks resolved (itself when that fails: a loop, say)."""
    with contextlib.suppress(OSError, RuntimeError):
        return str(Path(lexical).resolve())
    return lexical


def _file_id(path: str) -> tuple[int, int] | None:
    """(device, inode) of the file ``path`` names, following symlinks; None when none."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


class _SameFile:
    """Whether a recorded path names what a key names: the same absolute path, lexically or
    with symlinks resolved on either side. Resolving a path costs a system call per component
    (~70 us), too much for every mesh of a large catalogue, so a mesh path is resolved only
    where it can match: where the key names an existing file, paths of that file's (device,
    inode) (one ``stat``); where it names none, paths that name none either (a resolved path
    equal to the key's resolved one names the same file, or, missing, none)."""

    def __init__(self, key: str):
        lex = _lexical(key)
        self.wanted = {lex, _resolved(lex)}
        self.file = _file_id(lex)

    def is_(self, path: str) -> bool:
        lex = _lexical(path)
        if lex in self.wanted:
            return True
        if _file_id(lex) != self.file:
            return False
        return _resolved(lex) in self.wanted
