"""Shared by the writer and the reader: on-disk layout, SQL schema, canonical JSON, opening checks.

Layout of a catalogue directory ``ROOT`` (see ``ucad_catalog/SCHEMA.md``)::

    ROOT/catalog.sqlite            SQLite index, WAL mode
    ROOT/objects/<sha[:2]>/<sha>   artifacts, named by the sha256 of their bytes
    ROOT/write.lock                held (flock) by the single writer while it is open

Nothing here imports OpenCL.
"""
from __future__ import annotations

import hashlib
import json
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np

SCHEMA_VERSION = 2              # 2: meshes.orientation (1 is read, and migrated by the writer)
READABLE_VERSIONS = (1, 2)
FORMAT_NAME = "ucad-catalog"
DB_NAME = "catalog.sqlite"
OBJECTS_DIR = "objects"
LOCK_NAME = "write.lock"


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
    orientation  TEXT NOT NULL DEFAULT '{}'
);
CREATE INDEX meshes_path ON meshes(path);
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


def check_catalog_db(conn: sqlite3.Connection, where: Path) -> int:
    """The schema version of the ucad catalogue ``conn``; CatalogError unless it is one this
    code reads (READABLE_VERSIONS)."""
    try:
        rows = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    except sqlite3.DatabaseError as exc:   # not a database, or no meta table
        raise CatalogError(f"not a ucad catalogue: {where} ({exc})") from None
    if rows.get("format") != FORMAT_NAME:
        raise CatalogError(f"not a ucad catalogue: {where} (meta.format={rows.get('format')!r})")
    version = int(rows.get("schema_version", -1))
    if version not in READABLE_VERSIONS:
        raise CatalogError(f"{where}: catalogue schema_version {version}, this code reads "
                           f"schema_version {SCHEMA_VERSION}")
    return version


def migrate(conn: sqlite3.Connection) -> None:
    """Bring a readable older catalogue to SCHEMA_VERSION in one transaction (the writer
    does this when it opens one): 1 -> 2 adds ``meshes.orientation`` ('{}' for old rows)."""
    if orientation_column(conn) == "orientation":
        return
    conn.execute("BEGIN IMMEDIATE")
    try:
        conn.execute("ALTER TABLE meshes ADD COLUMN orientation TEXT NOT NULL DEFAULT '{}'")
        conn.execute("UPDATE meta SET value=? WHERE key='schema_version'", (str(SCHEMA_VERSION),))
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise


def orientation_column(conn: sqlite3.Connection) -> str:
    """SQL for the meshes' orientation JSON: the column, or '{}' in a version 1 catalogue."""
    cols = {r[1] for r in conn.execute("PRAGMA table_info(meshes)")}
    return "orientation" if "orientation" in cols else "'{}'"


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


def mesh_records(conn: sqlite3.Connection, where: str = "", args: tuple = ()) -> list[dict]:
    """Full plain-JSON records of meshes (ordered by mesh id): the export / round-trip format."""
    out = []
    for row in conn.execute(
            "SELECT id, sha256, path, size, mtime, state, reason, detail, n_triangles, "
            f"n_materials, file_to_norm, options_hash, run_id, timings, "
            f"{orientation_column(conn)} FROM meshes {where} ORDER BY id", args).fetchall():
        mid = row[0]
        rec = dict(zip(("id", "sha256", "path", "size", "mtime", "state", "reason", "detail",
                        "n_triangles", "n_materials"), row[:10]))
        rec["file_to_norm"] = json.loads(row[10])
        rec["options_hash"], rec["run_id"], rec["timings"] = row[11], row[12], json.loads(row[13])
        rec["orientation"] = json.loads(row[14])
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
