"""Shared by the writer and the reader: on-disk layout, SQL schema, canonical JSON, opening checks.

Layout of a catalogue directory ``ROOT`` (see ``ucad_catalog/SCHEMA.md``)::

    ROOT/catalog.sqlite            SQLite index, WAL mode
    ROOT/objects/<sha[:2]>/<sha>   artifacts, named by the sha256 of their bytes
    ROOT/write.lock                held (flock) by the single writer while it is open
    ROOT/search_index.npz          derived, optional: the features projected for retrieval

Nothing here imports OpenCL.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sqlite3
import zipfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from numpy.lib import format as npy

SCHEMA_VERSION = 2
UPGRADABLE = {1: """
ALTER TABLE meshes ADD COLUMN library_root TEXT NOT NULL DEFAULT '';
ALTER TABLE meshes ADD COLUMN orientation TEXT;
ALTER TABLE meshes ADD COLUMN meta TEXT NOT NULL DEFAULT '{}';
DROP INDEX meshes_path;
CREATE INDEX meshes_path ON meshes(library_root, path);
"""}                                  # schema_version -> SQL that brings it to SCHEMA_VERSION
FORMAT_NAME = "ucad-catalog"
DB_NAME = "catalog.sqlite"
OBJECTS_DIR = "objects"
LOCK_NAME = "write.lock"
SEARCH_INDEX = "search_index.npz"   # derived: projected features for retrieval (searchindex.py)
INDEX_UNREADABLE = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)  # np.load of a bad .npz


# the artifact kinds the build writes (SCHEMA.md, "Artifact kinds", is tested against this);
# other kinds are allowed (any non-empty name without '/')
ARTIFACT_KINDS = {
    "views.exr": "the view stack: tri, mat, Z per view + cameras (ucad_catalog.exr, format 2)",
    "views.npz": "fallback view stack: NumPy .npz with tri_id u32, mat_id u16, depth f32, "
                 "each (V, H, W)",
    "edges.npy.gz": "Canny edges of the material maps of the label ring (the first "
                    "`--elevations` ring, views 0..V-1; the build's default stores 2V views, the "
                    "second ring without edges): gzip of an .npy (V, H, ceil(W/8)) uint8, "
                    "np.packbits(edges > 0, axis=-1); unpack with np.unpackbits(axis=-1, count=W)",
    "features.npy": "(V, D) float32 pose features (HOG of the shaded views), np.save, no pickle",
    "parts.png": "contact sheet of up to 24 views coloured by part, legend on the right (PNG)",
}


class CatalogError(Exception):
    """Any problem with a catalogue: missing or foreign path, bad entry, missing artifact."""


SCHEMA_SQL = """
CREATE TABLE meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE runs (
    id           INTEGER PRIMARY KEY,
    started      REAL NOT NULL,
    finished     REAL,
    options_hash TEXT NOT NULL,
    options      TEXT NOT NULL,
    engine       TEXT NOT NULL,
    counts       TEXT,
    meshes_per_s REAL
);
CREATE TABLE meshes (
    id           INTEGER PRIMARY KEY,
    sha256       TEXT NOT NULL UNIQUE,
    path         TEXT NOT NULL,
    size         INTEGER NOT NULL,
    mtime        REAL NOT NULL,
    state        TEXT NOT NULL CHECK (state IN ('accepted', 'rejected')),
    reason       TEXT NOT NULL DEFAULT '',
    detail       TEXT NOT NULL DEFAULT '',
    n_triangles  INTEGER NOT NULL,
    n_materials  INTEGER NOT NULL,
    file_to_norm TEXT NOT NULL,
    options_hash TEXT NOT NULL,
    run_id       INTEGER NOT NULL REFERENCES runs(id),
    timings      TEXT NOT NULL,
    library_root TEXT NOT NULL DEFAULT '',
    orientation  TEXT,
    meta         TEXT NOT NULL DEFAULT '{}'
);
CREATE INDEX meshes_path ON meshes(library_root, path);
CREATE INDEX meshes_state ON meshes(state, reason);
CREATE TABLE materials (
    mesh_id  INTEGER NOT NULL REFERENCES meshes(id) ON DELETE CASCADE,
    idx      INTEGER NOT NULL,
    name     TEXT NOT NULL,
    part     TEXT NOT NULL,
    score    REAL NOT NULL,
    iou      REAL NOT NULL,
    view     INTEGER NOT NULL,
    decision TEXT NOT NULL,
    pixels   INTEGER NOT NULL,
    props    TEXT NOT NULL,
    PRIMARY KEY (mesh_id, idx)
);
CREATE TABLE views (
    mesh_id   INTEGER NOT NULL REFERENCES meshes(id) ON DELETE CASCADE,
    view      INTEGER NOT NULL,
    azimuth   REAL NOT NULL,
    elevation REAL NOT NULL,
    K         TEXT NOT NULL,
    w2c       TEXT NOT NULL,
    stats     TEXT NOT NULL,
    PRIMARY KEY (mesh_id, view)
);
CREATE TABLE artifacts (
    mesh_id INTEGER NOT NULL REFERENCES meshes(id) ON DELETE CASCADE,
    kind    TEXT NOT NULL,
    sha256  TEXT NOT NULL,
    bytes   INTEGER NOT NULL,
    PRIMARY KEY (mesh_id, kind)
);
CREATE INDEX artifacts_sha ON artifacts(sha256);
CREATE VIEW rejections AS
    SELECT id, sha256, path, reason, detail, run_id FROM meshes WHERE state = 'rejected';
"""


def canonical_json(obj: Any) -> str:
    """Deterministic JSON: sorted keys, no spaces, NumPy scalars/arrays as plain numbers/lists.

    Floats are written with ``repr`` (shortest round-trip form), so float64 values read back
    bit-identically. NaN/inf are refused (``ValueError``): they are not JSON.
    """
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False, default=_json_default)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def options_hash(options: dict) -> str:
    """sha256 of the canonical JSON of ``options`` without its top-level ``"runtime"`` key.

    Put settings that do not change results (worker count, device, progress bars) under
    ``options["runtime"]``; everything else is part of the hash and a change re-processes meshes.
    """
    if not isinstance(options, dict):
        raise CatalogError(f"options must be a dict, got {type(options).__name__}")
    hashed = {k: v for k, v in options.items() if k != "runtime"}
    return hashlib.sha256(canonical_json(hashed).encode("utf-8")).hexdigest()


def is_sha256(text: Any) -> bool:
    return (isinstance(text, str) and len(text) == 64
            and all(c in "0123456789abcdef" for c in text))


def object_path(root: Path, sha: str) -> Path:
    return root / OBJECTS_DIR / sha[:2] / sha


def check_catalog_db(conn: sqlite3.Connection, where: Path, upgrade: bool = False) -> None:
    """Raise CatalogError unless ``conn`` is a ucad catalogue of this schema version.

    ``upgrade`` (the writer): an older version listed in ``UPGRADABLE`` is brought to this one
    in one transaction; the read-only reader says how to upgrade instead."""
    try:
        rows = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    except sqlite3.DatabaseError as exc:   # not a database, or no meta table
        raise CatalogError(f"not a ucad catalogue: {where} ({exc})") from None
    if rows.get("format") != FORMAT_NAME:
        raise CatalogError(f"not a ucad catalogue: {where} (meta.format={rows.get('format')!r})")
    version = int(rows.get("schema_version", -1))
    if version in UPGRADABLE and upgrade:
        conn.executescript("BEGIN IMMEDIATE;" + UPGRADABLE[version]
                           + f"UPDATE meta SET value='{SCHEMA_VERSION}' WHERE key='schema_version';"
                           + "COMMIT;")
        return
    if version in UPGRADABLE:
        raise CatalogError(f"{where}: catalogue schema_version {version}, this code reads "
                           f"schema_version {SCHEMA_VERSION}; upgrade it in place once with "
                           f"`ucad-index status --catalog {Path(where).parent}` (needs write "
                           "access)")
    if version != SCHEMA_VERSION:
        raise CatalogError(f"{where}: catalogue schema_version {version}, this code reads "
                           f"schema_version {SCHEMA_VERSION}")


def locate_db(path: str | Path) -> tuple[Path, Path]:
    """(root, db path) of an existing catalogue directory, or CatalogError naming the problem."""
    root = Path(path)
    if not root.exists():
        raise CatalogError(f"no catalogue at {root}: path does not exist")
    if not root.is_dir():
        raise CatalogError(f"not a catalogue: {root} is a file; a catalogue is a directory "
                           f"holding {DB_NAME} and {OBJECTS_DIR}/")
    db = root / DB_NAME
    if not db.is_file():
        raise CatalogError(f"not a catalogue: {root} has no {DB_NAME}")
    return root, db


# the one order of meshes everywhere (reader listings, exports): independent of commit order,
# so builds with any number of workers list and export the same rows
MESH_ORDER = "library_root, path, sha256"


def feature_key(conn: sqlite3.Connection) -> tuple[tuple[str, str | None], ...]:
    """(mesh sha256, its ``features.npy`` object sha256 or None) of every accepted mesh, in
    ``MESH_ORDER``: what the stacked features (``FeatureTable``, the search index) depend on."""
    order = ", ".join(f"m.{c.strip()}" for c in MESH_ORDER.split(","))
    return tuple(conn.execute(
        "SELECT m.sha256, a.sha256 FROM meshes m LEFT JOIN artifacts a ON a.mesh_id=m.id AND "
        f"a.kind='features.npy' WHERE m.state='accepted' ORDER BY {order}").fetchall())


def feature_key_hash(key) -> str:
    """sha256 (hex) of a feature key: [(mesh sha256, features object sha256 or None)]."""
    return hashlib.sha256(canonical_json([list(p) for p in key]).encode()).hexdigest()


def feature_objects(root: Path, key) -> tuple[list[tuple[str, Path, tuple[int, ...], bool]],
                                               list[tuple[str, str]]]:
    """The ``features.npy`` objects of a feature key (``feature_key``), in its order:
    [(mesh sha256, path, shape, raw)] of those whose header reads (``npy_header``), and
    [(mesh sha256, why)] of the others (no object: built with --no-features; unreadable)."""
    items, skipped = [], []
    for sha, obj in key:
        if obj is None:
            skipped.append((sha, "no features.npy (built with --no-features)"))
            continue
        path = object_path(root, obj)
        try:
            shape, raw = npy_header(path)
        except (OSError, ValueError, EOFError) as exc:
            skipped.append((sha, f"features.npy unreadable ({exc})"))
            continue
        items.append((sha, path, shape, raw))
    return items, skipped


def open_search_index(root: Path):
    """``root/SEARCH_INDEX`` opened (``np.load``: a ``NpzFile``, to be closed; members are read
    when asked for), or None when there is none; ValueError (or OSError, zipfile.BadZipFile)
    when it cannot be read, or when its members declare more bytes than the file holds (the
    writer only stores: a compressed bomb is refused before any member is inflated)."""
    path = Path(root) / SEARCH_INDEX
    if not path.is_file():
        return None
    z = np.load(path, allow_pickle=False)
    try:
        declared = sum(i.file_size for i in z.zip.infolist())
        if declared > os.fstat(z.fid.fileno()).st_size:
            raise ValueError(f"its members declare {declared} bytes, more than the file's")
    except BaseException:
        z.close()
        raise
    return z


def search_index_key(root: Path) -> str | None:
    """The ``key`` stored in ``root/SEARCH_INDEX`` (None when there is none; errors as
    ``open_search_index``)."""
    z = open_search_index(root)
    if z is None:
        return None
    with z:
        return str(z["key"])


def mesh_records(conn: sqlite3.Connection, where: str = "", args: tuple = ()) -> list[dict]:
    """Full plain-JSON records of meshes (in ``MESH_ORDER``), ``CatalogReader.record``'s format.
    ``id`` is the internal row id (commit order); the public id is ``sha256``."""
    out = []
    for row in conn.execute(
            "SELECT id, sha256, path, size, mtime, state, reason, detail, n_triangles, "
            "n_materials, file_to_norm, options_hash, run_id, timings, library_root, "
            f"orientation, meta FROM meshes {where} ORDER BY {MESH_ORDER}", args).fetchall():
        mid = row[0]
        rec = dict(zip(("_rowid", "sha256", "path", "size", "mtime", "state", "reason", "detail",
                        "n_triangles", "n_materials"), row[:10]))
        rec["file_to_norm"] = json.loads(row[10])
        rec["options_hash"], rec["run_id"], rec["timings"] = row[11], row[12], json.loads(row[13])
        rec["library_root"] = row[14]
        rec["orientation"] = json.loads(row[15]) if row[15] is not None else None
        rec["meta"] = json.loads(row[16])
        del rec["_rowid"]                   # internal (commit order); the public id is the hash
        rec["id"] = rec["sha256"]
        rec["materials"] = [
            {"index": r[0], "name": r[1], "part": r[2], "score": r[3], "iou": r[4], "view": r[5],
             "decision": r[6], "pixels": r[7], "props": json.loads(r[8])}
            for r in conn.execute("SELECT idx, name, part, score, iou, view, decision, pixels, "
                                  "props FROM materials WHERE mesh_id=? ORDER BY idx", (mid,))]
        rec["views"] = [
            {"index": r[0], "azimuth": r[1], "elevation": r[2], "K": json.loads(r[3]),
             "w2c": json.loads(r[4]), "stats": json.loads(r[5])}
            for r in conn.execute("SELECT view, azimuth, elevation, K, w2c, stats FROM views "
                                  "WHERE mesh_id=? ORDER BY view", (mid,))]
        rec["artifacts"] = {
            r[0]: {"sha256": r[1], "bytes": r[2]}
            for r in conn.execute("SELECT kind, sha256, bytes FROM artifacts WHERE mesh_id=? "
                                  "ORDER BY kind", (mid,))}
        out.append(rec)
    return out


# ----------------------------------------------------------------------------- shared read paths
# Used by both the writer (``Catalog``) and the reader (``CatalogReader``): none takes the lock.

TMP_PREFIX = ".tmp-"


def printable(text: str) -> str:
    """``text`` as valid UTF-8 for SQLite and JSON: the bytes of a non-UTF-8 file name (Python's
    surrogate escapes) become ``\\xNN``, other lone surrogates ``\\udNNN``; valid text unchanged."""
    text = text if isinstance(text, str) else str(text)
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


RECENT_RUNS = 5      # runs that ``status`` lists (newest first)


@contextlib.contextmanager
def read_snapshot(conn: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    """Reads inside the block see one committed state. Inside a transaction already (a
    ``CatalogReader.snapshot()`` block, the writer's transaction) it joins it instead of
    starting one, so snapshot readers nest."""
    if conn.in_transaction:
        yield conn
        return
    conn.execute("BEGIN")
    try:
        yield conn
    finally:
        conn.execute("COMMIT")


def run_rows(conn: sqlite3.Connection, n: int) -> list[dict]:
    """The last ``n`` runs, newest first: id, started, finished (s since the epoch; finished
    None while running or after a kill), engine, options_hash, counts, meshes_per_s."""
    rows = conn.execute("SELECT id, started, finished, engine, options_hash, counts, "
                        "meshes_per_s FROM runs ORDER BY id DESC LIMIT ?", (int(n),)).fetchall()
    return [{"id": r[0], "started": r[1], "finished": r[2], "engine": r[3],
             "options_hash": r[4], "counts": json.loads(r[5]) if r[5] else {},
             "meshes_per_s": r[6]} for r in rows]


def catalog_status(conn: sqlite3.Connection, root: Path, recent: int = RECENT_RUNS) -> dict:
    """Counts by state and by rejection reason, accepted meshes flagged by reason
    (``uncertain_orientation``), object totals, the number of runs and the ``recent`` last
    ones (``run_rows``), all in one snapshot (``read_snapshot``). SCHEMA.md, 'Command output',
    documents the keys."""
    with read_snapshot(conn):
        by_state = {"accepted": 0, "rejected": 0}
        by_state.update(dict(conn.execute("SELECT state, count(*) FROM meshes GROUP BY state")))
        by_reason = dict(conn.execute("SELECT reason, count(*) FROM meshes WHERE "
                                      "state='rejected' GROUP BY reason ORDER BY reason"))
        # accepted meshes with a note: an orientation estimate under the confidence threshold
        # (the record is canonical JSON, so the key and value are written without spaces)
        flagged = {"uncertain_orientation": conn.execute(
            "SELECT count(*) FROM meshes WHERE state='accepted' AND orientation IS NOT NULL "
            "AND instr(orientation, '\"uncertain\":true') > 0").fetchone()[0]}
        n_obj, n_bytes = conn.execute("SELECT count(*), coalesce(sum(bytes), 0) FROM "
                                      "(SELECT DISTINCT sha256, bytes FROM artifacts)").fetchone()
        n_runs = conn.execute("SELECT count(*) FROM runs").fetchone()[0]
        runs = run_rows(conn, max(int(recent), 1))
        key = feature_key(conn)
    try:
        stored = search_index_key(root)
        index = ("none" if stored is None else
                 "fresh" if stored == feature_key_hash(key) else "stale")
    except INDEX_UNREADABLE:
        index = "unreadable"
    return {"root": str(root), "schema_version": SCHEMA_VERSION,
            "meshes": sum(by_state.values()), "by_state": by_state,
            "by_reason": by_reason, "flagged": flagged, "objects": n_obj,
            "object_bytes": n_bytes, "n_runs": n_runs, "runs": runs[:max(int(recent), 0)],
            "last_run": runs[0] if runs else None, "search_index": index}


def remove_stale_exports(out: Path) -> None:
    """Delete ``.tmp-<name>.<pid>.*`` files next to ``out`` whose exporting process is gone
    (``ucad_catalog.export`` names its temporary files so)."""

    prefix = f"{TMP_PREFIX}{out.name}."
    try:
        siblings = list(out.parent.iterdir())
    except OSError:
        return
    for p in siblings:
        if not p.name.startswith(prefix):
            continue
        pid = p.name[len(prefix):].split(".", 1)[0]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            p.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def verify_catalog(conn: sqlite3.Connection, root: Path, rehash: bool = True) -> dict:
    """Read-only consistency check. Returns ``{"problems": [...], "unreferenced": [(name,
    bytes)], "tmp_files": [(name, bytes)], "objects": n, "bytes": n}``.

    Problems (the catalogue is damaged): ``PRAGMA integrity_check`` and ``foreign_key_check``
    findings, referenced objects that are missing, or whose size or sha256 (with ``rehash``)
    does not match their name. Not problems (``gc`` reclaims them): objects nothing references
    (a killed build's last objects, superseded artifacts) and ``.tmp-*`` files; while a build
    runs, the objects it is about to commit also show as unreferenced.
    """
    problems: list[str] = []
    conn.execute("BEGIN")
    try:
        for (line,) in conn.execute("PRAGMA integrity_check"):
            if line != "ok":
                problems.append(f"integrity: {line}")
        for row in conn.execute("PRAGMA foreign_key_check"):
            problems.append(f"foreign key: table {row[0]} rowid {row[1]} -> {row[2]}")
        refs = conn.execute("SELECT DISTINCT sha256, bytes FROM artifacts ORDER BY sha256"
                            ).fetchall()
    finally:
        conn.execute("COMMIT")
    live = set()
    total = 0
    for sha, n in refs:
        live.add(sha)
        p = object_path(root, sha)
        if not p.is_file():
            problems.append(f"missing object {sha}")
            continue
        size = p.stat().st_size
        total += size
        if size != n:
            problems.append(f"corrupt object {sha}: {size} bytes, expected {n}")
        elif rehash:
            h = hashlib.sha256()
            with open(p, "rb") as f:
                while chunk := f.read(1 << 20):
                    h.update(chunk)
            if h.hexdigest() != sha:
                problems.append(f"corrupt object {sha}: content does not match its name")
    unreferenced, tmp_files = [], []
    objects = root / OBJECTS_DIR
    shards = sorted(p for p in objects.iterdir() if p.is_dir()) if objects.is_dir() else []
    for shard in shards:
        for obj in sorted(shard.iterdir()):
            if obj.name.startswith(TMP_PREFIX):
                tmp_files.append((f"{shard.name}/{obj.name}", obj.stat().st_size))
            elif obj.name not in live:
                unreferenced.append((f"{shard.name}/{obj.name}", obj.stat().st_size))
    return {"problems": problems, "unreferenced": unreferenced, "tmp_files": tmp_files,
            "objects": len(live), "bytes": total}


def npy_header(path: Path) -> tuple[tuple[int, ...], bool]:
    """(shape, raw) of a ``.npy`` file: ``raw`` when its data are little-endian float32 in C
    order, exactly filling the file after the header (so they can be read into place);
    ValueError for a file that is not a ``.npy``, holds no real numbers or is shorter than its
    header says."""
    with open(path, "rb") as f:
        version = npy.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = npy.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = npy.read_array_header_2_0(f)
        else:
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
            if arr.dtype.kind not in "fiu":
                raise ValueError(f"dtype {arr.dtype} is not a real number type")
            return tuple(arr.shape), False
        data = os.fstat(f.fileno()).st_size - f.tell()
    if dtype.kind not in "fiu":
        raise ValueError(f"dtype {dtype} is not a real number type")
    need = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if data < need:
        raise ValueError(f"{data} bytes of data, its header says {need}")
    raw = dtype == np.dtype("<f4") and not fortran and data == need
    return tuple(shape), bool(raw)


def will_need(fd: int, offset: int, length: int) -> None:
    """Ask the kernel to start reading bytes ``offset .. offset + length`` of the open file
    ``fd`` into the page cache (``posix_fadvise(POSIX_FADV_WILLNEED)``: it returns at once),
    so that reads of many scattered places wait for the disk together, not one after
    another; nothing where the call does not exist (macOS, Windows) or is refused."""
    advise = getattr(os, "posix_fadvise", None)
    if advise is not None and length > 0:
        try:
            advise(fd, offset, length, os.POSIX_FADV_WILLNEED)
        except OSError:
            pass
