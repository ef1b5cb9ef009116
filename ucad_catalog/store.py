"""The catalogue writer: SQLite (WAL) index + content-addressed artifact objects.

Crash safety (kill -9 at any moment leaves, for each mesh, either nothing or everything):

1. every artifact is written to ``objects/<sha[:2]>/.tmp-*`` in its final folder, fsynced, renamed
   to ``objects/<sha[:2]>/<sha>`` (sha256 of its bytes) and the folder fsynced;
2. only then are all index rows of the mesh written in ONE SQLite transaction (synchronous=FULL).

A crash between 1 and 2 leaves orphan objects that nothing references; ``gc()`` removes them.
One writer at a time (``write.lock`` is flock-ed while a ``Catalog`` is open); readers
(``ucad_catalog.reader``) may read concurrently thanks to WAL.

Re-processing policy (``needs_processing``): a mesh is skipped iff a row with the same content
sha256 AND the same options hash exists (accepted or rejected). Changed file -> new sha ->
processed; on commit the row previously held by the same path is deleted in the same
transaction. Changed options -> processed; on commit the row of the same sha is replaced in
place (its mesh id is kept, children rows rewritten) in one transaction. Options under the
top-level key ``"runtime"`` are not hashed (see ``options_hash``).

Times are Unix seconds (float). No OpenCL here.
"""
from __future__ import annotations

import errno
import hashlib
import os
import sqlite3
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from ._db import (DB_NAME, FORMAT_NAME, LOCK_NAME, OBJECTS_DIR, RECENT_RUNS, SCHEMA_SQL,
                  SCHEMA_VERSION, TMP_PREFIX, CatalogError, canonical_json, catalog_status,
                  check_catalog_db, is_sha256, mesh_records, object_path, options_hash, printable,
                  verify_catalog)
from .entry import CatalogEntry
from .export import format_for, write_export

try:                                   # POSIX advisory lock for the single-writer rule
    import fcntl
except ImportError:                    # pragma: no cover - non-POSIX: lock not enforced
    fcntl = None  # type: ignore[assignment]

_CHUNK = 1 << 20
_TMP_PREFIX = TMP_PREFIX


class Catalog:
    """Writer handle. ``Catalog.open(root)`` -> ``begin_run`` -> ``commit_mesh``* -> ``finish_run``."""

    def __init__(self, root: Path, conn: sqlite3.Connection, lock_fd: int | None,
                 durable: bool = True):
        self.root = root
        self.durable = durable
        self._conn: sqlite3.Connection | None = conn
        self._lock_fd = lock_fd
        self._run_id: int | None = None
        self._run_hash: str | None = None
        self.superseded_bytes = 0    # objects that lost their last reference in this session

    # ------------------------------------------------------------------ open / close
    @classmethod
    def open(cls, path: str | Path, create: bool = True, durable: bool = True) -> "Catalog":
        """Open (or create, if ``create`` and absent/empty) the catalogue directory ``path``.

        ``durable=False`` skips the fsyncs (SQLite synchronous=NORMAL): still all-or-nothing
        per mesh if the process is killed, but a power loss may lose the last commits.
        """
        root = Path(path)
        if root.exists() and not root.is_dir():
            raise CatalogError(f"not a catalogue: {root} is a file; a catalogue is a directory")
        if not root.exists():
            if not create:
                raise CatalogError(f"no catalogue at {root}: path does not exist")
            root.mkdir(parents=True)
        db = root / DB_NAME
        if not db.exists():
            if not create:
                raise CatalogError(f"not a catalogue: {root} has no {DB_NAME}")
            foreign = sorted(p.name for p in root.iterdir() if p.name not in (LOCK_NAME,
                                                                               OBJECTS_DIR))
            if foreign:
                raise CatalogError(f"not a catalogue: {root} has no {DB_NAME} and is not empty "
                                   f"({', '.join(foreign[:3])}...); refusing to create one there")
        lock_fd = _take_lock(root)
        try:
            conn = sqlite3.connect(str(db), isolation_level=None, timeout=30.0)
            try:
                n_tables = conn.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]
            except sqlite3.DatabaseError as exc:
                conn.close()
                raise CatalogError(f"not a ucad catalogue: {db} ({exc})") from None
            if n_tables == 0:
                if not create:
                    conn.close()
                    raise CatalogError(f"not a ucad catalogue: {db} is empty")
                _init_schema(conn)
            check_catalog_db(conn, db, upgrade=True)
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute(f"PRAGMA synchronous={'FULL' if durable else 'NORMAL'}")
            conn.execute("PRAGMA foreign_keys=ON")
            (root / OBJECTS_DIR).mkdir(exist_ok=True)
        except BaseException:
            _release_lock(lock_fd)
            raise
        return cls(root, conn, lock_fd, durable)

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        _release_lock(self._lock_fd)
        self._lock_fd = None

    def __enter__(self) -> "Catalog":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------ runs
    def begin_run(self, options: dict, engine: str) -> int:
        """Record a new run (options stored as canonical JSON) and make it current."""
        h = options_hash(options)
        cur = self._db.execute(
            "INSERT INTO runs (started, options_hash, options, engine) VALUES (?, ?, ?, ?)",
            (time.time(), h, canonical_json(options), str(engine)))
        assert cur.lastrowid is not None
        self._run_id, self._run_hash = int(cur.lastrowid), h
        return self._run_id

    @property
    def run_options_hash(self) -> str | None:
        """Options hash of the current run (None outside ``begin_run`` .. ``finish_run``)."""
        return self._run_hash

    def finish_run(self, run_id: int, stats: dict | None = None) -> dict:
        """Close run ``run_id``: counts = committed meshes by state + ``stats`` (e.g. skipped,
        failed); meshes/s = committed meshes / wall time unless ``stats['meshes_per_s']``."""
        row = self._db.execute("SELECT started FROM runs WHERE id=?", (run_id,)).fetchone()
        if row is None:
            raise CatalogError(f"{self.root}: no run with id {run_id}")
        stats = dict(stats or {})
        counts = {"accepted": 0, "rejected": 0}
        counts.update(dict(self._db.execute(
            "SELECT state, count(*) FROM meshes WHERE run_id=? GROUP BY state", (run_id,))))
        rate = stats.pop("meshes_per_s", None)
        counts.update(stats)
        finished = time.time()
        if rate is None:
            n = counts["accepted"] + counts["rejected"]
            rate = n / max(finished - row[0], 1e-9)
        self._db.execute("UPDATE runs SET finished=?, counts=?, meshes_per_s=? WHERE id=?",
                         (finished, canonical_json(counts), float(rate), run_id))
        if run_id == self._run_id:
            self._run_id = self._run_hash = None
        return {"run_id": run_id, "counts": counts, "meshes_per_s": float(rate)}

    # ------------------------------------------------------------------ meshes
    def needs_processing(self, path: str | Path, sha: str, options_hash: str) -> bool:
        """False iff a mesh with content ``sha`` was committed with ``options_hash`` (see module
        docstring for the policy). ``path`` is accepted for symmetry and logging only."""
        if not is_sha256(sha):
            raise CatalogError(f"{path}: sha must be a sha256 hex digest, got {sha!r}")
        row = self._db.execute("SELECT options_hash FROM meshes WHERE sha256=?",
                               (sha,)).fetchone()
        return row is None or row[0] != options_hash

    def file_record(self, path: str | Path,
                    library_root: str = "") -> tuple[str, int, float] | None:
        """(sha256, size, mtime) last committed for ``path`` (relative to ``library_root``), to
        skip re-hashing unchanged files."""
        row = self._db.execute("SELECT sha256, size, mtime FROM meshes WHERE library_root=? "
                               "AND path=? ORDER BY id DESC LIMIT 1",
                               (printable(str(library_root)), printable(str(path)))).fetchone()
        return None if row is None else (row[0], int(row[1]), float(row[2]))

    def mesh_verdict(self, sha: str) -> tuple[str, str, str] | None:
        """(state, reason, options_hash) of content ``sha``, or None when it is not catalogued."""
        row = self._db.execute("SELECT state, reason, options_hash FROM meshes WHERE sha256=?",
                               (sha,)).fetchone()
        return None if row is None else (row[0], row[1], row[2])

    def commit_mesh(self, entry: CatalogEntry, *, move_files: bool = False) -> int:
        """Store the artifacts, then all rows of ``entry`` in one transaction; returns mesh id.

        ``move_files``: file artifacts (``Path``) are the caller's to give away (a build's staging
        files): they are renamed into the object store instead of copied when they are on the
        catalogue's file system (and removed when the object already exists)."""
        if self._run_id is None:
            raise CatalogError(f"{self.root}: commit_mesh({entry.path!r}) before begin_run")
        entry.validate()
        opt_hash = entry.options_hash or self._run_hash
        stored = {kind: self._put_object(data, kind, entry.path, move=move_files)
                  for kind, data in sorted(entry.artifacts.items())}
        conn = self._db
        path = printable(entry.path)                        # text columns are valid UTF-8
        conn.execute("BEGIN IMMEDIATE")
        try:
            root = printable(entry.library_root)
            old = conn.execute("SELECT DISTINCT a.sha256, a.bytes FROM artifacts a JOIN meshes m "
                               "ON a.mesh_id=m.id WHERE (m.library_root=? AND m.path=? AND "
                               "m.sha256<>?) OR m.sha256=?",
                               (root, path, entry.sha256, entry.sha256)).fetchall()
            conn.execute("DELETE FROM meshes WHERE library_root=? AND path=? AND sha256<>?",
                         (root, path, entry.sha256))          # changed file: old out
            values = (path, int(entry.size), float(entry.mtime), entry.state,
                      printable(entry.reason), printable(entry.detail), int(entry.n_triangles),
                      int(entry.n_materials), canonical_json(_floats(entry.file_to_norm)),
                      opt_hash, self._run_id, printable(canonical_json(entry.timings)), root,
                      None if entry.orientation is None
                      else printable(canonical_json(entry.orientation)),
                      printable(canonical_json(entry.meta)))
            row = conn.execute("SELECT id FROM meshes WHERE sha256=?",
                               (entry.sha256,)).fetchone()
            mid: int | None
            if row is None:
                mid = conn.execute(
                    "INSERT INTO meshes (path, size, mtime, state, reason, detail, n_triangles, "
                    "n_materials, file_to_norm, options_hash, run_id, timings, library_root, "
                    "orientation, meta, sha256) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                    values + (entry.sha256,)).lastrowid
            else:                                              # re-processed: keep the id
                mid = row[0]
                conn.execute(
                    "UPDATE meshes SET path=?, size=?, mtime=?, state=?, reason=?, detail=?, "
                    "n_triangles=?, n_materials=?, file_to_norm=?, options_hash=?, run_id=?, "
                    "timings=?, library_root=?, orientation=?, meta=? WHERE id=?",
                    values + (mid,))
                for table in ("materials", "views", "artifacts"):
                    conn.execute(f"DELETE FROM {table} WHERE mesh_id=?", (mid,))
            conn.executemany(
                "INSERT INTO materials (mesh_id, idx, name, part, score, iou, view, decision, "
                "pixels, props) VALUES (?,?,?,?,?,?,?,?,?,?)",
                [(mid, int(m.index), printable(m.name), printable(m.part), float(m.score),
                  float(m.iou), int(m.view), printable(m.decision), int(m.pixels),
                  printable(canonical_json(m.props)))
                 for m in sorted(entry.materials, key=lambda m: m.index)])
            conn.executemany(
                "INSERT INTO views (mesh_id, view, azimuth, elevation, K, w2c, stats) "
                "VALUES (?,?,?,?,?,?,?)",
                [(mid, int(v.index), float(v.azimuth), float(v.elevation),
                  canonical_json(_floats(v.K)), canonical_json(_floats(v.w2c)),
                  printable(canonical_json(v.stats)))
                 for v in sorted(entry.views, key=lambda v: v.index)])
            conn.executemany(
                "INSERT INTO artifacts (mesh_id, kind, sha256, bytes) VALUES (?,?,?,?)",
                [(mid, kind, sha, n) for kind, (sha, n) in stored.items()])
            gone = [(sha, n) for sha, n in old if conn.execute(
                "SELECT 1 FROM artifacts WHERE sha256=? LIMIT 1", (sha,)).fetchone() is None]
            conn.execute("COMMIT")
        except BaseException:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            raise
        self.superseded_bytes += sum(n for _, n in gone)   # left for gc(): readers may hold them
        assert mid is not None
        return int(mid)

    # ------------------------------------------------------------------ maintenance
    def status(self, recent: int = RECENT_RUNS) -> dict:
        """Counts by state and by rejection reason, object totals, the run count and the
        ``recent`` last runs (``CatalogReader.status``)."""
        return catalog_status(self._db, self.root, recent)

    def export(self, path: str | Path, format: str | None = None) -> int:
        """Write the meshes table to ``path`` and the materials table beside it; returns the
        mesh count. Format from ``format`` or the suffix (.parquet / .jsonl); see
        ``ucad_catalog.export``."""

        format_for(path, format)                    # a bad format fails before any reading
        self._db.execute("BEGIN")                   # one consistent snapshot
        try:
            records = mesh_records(self._db)
        finally:
            self._db.execute("COMMIT")
        return write_export(records, path, format)

    def gc(self) -> dict:
        """Delete objects no artifact row references and leftover temporary files."""
        live = {r[0] for r in self._db.execute("SELECT DISTINCT sha256 FROM artifacts")}
        removed = tmp_removed = freed = 0
        objects = self.root / OBJECTS_DIR
        for shard in sorted(p for p in objects.iterdir() if p.is_dir()):
            for f in sorted(shard.iterdir()):
                if f.name.startswith(_TMP_PREFIX):
                    tmp_removed += 1
                elif f.name not in live:
                    removed += 1
                else:
                    continue
                freed += f.stat().st_size
                f.unlink()
            if not any(shard.iterdir()):
                shard.rmdir()
        return {"objects_removed": removed, "tmp_removed": tmp_removed, "bytes_freed": freed}

    def verify_report(self, rehash: bool = True) -> dict:
        """The full consistency report (``_db.verify_catalog``), unreferenced objects included."""
        return verify_catalog(self._db, self.root, rehash)

    def verify(self) -> list[str]:
        """Problems found (empty list = consistent): integrity and foreign-key checks, missing
        or corrupt referenced objects (re-hashed). See ``_db.verify_catalog`` for the full
        report, unreferenced objects included."""
        return verify_catalog(self._db, self.root)["problems"]

    # ------------------------------------------------------------------ internals
    @property
    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise CatalogError(f"catalogue {self.root} is closed")
        return self._conn

    def _put_object(self, data: bytes | str | Path, kind: str, owner: str,
                    move: bool = False) -> tuple[str, int]:
        """Write ``data`` (bytes or a file) as a content-addressed object; (sha256, bytes).
        ``move``: a file is renamed into place when possible (see ``commit_mesh``)."""
        if isinstance(data, (str, Path)):
            sha, n = _hash_file(Path(data))
        else:
            data = bytes(data)
            sha, n = hashlib.sha256(data).hexdigest(), len(data)
        final = object_path(self.root, sha)
        if final.is_file() and final.stat().st_size == n:
            if move and not isinstance(data, bytes):
                Path(data).unlink(missing_ok=True)
            return sha, n                            # already stored (renamed only when complete)
        shard = final.parent
        if not shard.is_dir():
            shard.mkdir(parents=True, exist_ok=True)
            if self.durable:
                _fsync_dir(shard.parent)
        if move and not isinstance(data, bytes) and self._move_into(Path(data), final, sha, n):
            return sha, n
        tmp = shard / f"{_TMP_PREFIX}{sha}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        try:
            with open(tmp, "wb") as f:
                if isinstance(data, bytes):
                    f.write(data)
                else:
                    h = hashlib.sha256()
                    with open(data, "rb") as src:
                        while chunk := src.read(_CHUNK):
                            h.update(chunk)
                            f.write(chunk)
                    if h.hexdigest() != sha:
                        raise CatalogError(f"{owner}: artifact {kind!r} file {data} changed "
                                           "while it was being stored")
                f.flush()
                if self.durable:
                    os.fsync(f.fileno())
            os.replace(tmp, final)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        if self.durable:
            _fsync_dir(shard)
        return sha, n

    def _move_into(self, src: Path, final: Path, sha: str, n: int) -> bool:
        """Rename the hashed file ``src`` to ``final`` (same file system only); False if not."""
        try:
            if self.durable:                         # its bytes on disk before the name is
                fd = os.open(src, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
            st = src.stat()
            if st.st_size != n:
                raise CatalogError(f"artifact file {src} changed while it was being stored")
            os.replace(src, final)
        except OSError as exc:
            if exc.errno == errno.EXDEV:             # another file system: copy instead
                return False
            raise
        if self.durable:
            _fsync_dir(final.parent)
        return True


def _init_schema(conn: sqlite3.Connection) -> None:
    """Create every table and the meta rows in one transaction (meta last)."""
    conn.execute("PRAGMA journal_mode=WAL")
    meta = (f"INSERT INTO meta VALUES ('format', '{FORMAT_NAME}');"
            f"INSERT INTO meta VALUES ('schema_version', '{SCHEMA_VERSION}');"
            f"INSERT INTO meta VALUES ('created', '{time.time()!r}');")
    conn.executescript("BEGIN;" + SCHEMA_SQL + meta + "COMMIT;")


def _floats(a: Any) -> list:
    return np.asarray(a, dtype=np.float64).tolist()


def _hash_file(path: Path) -> tuple[str, int]:
    h, n = hashlib.sha256(), 0
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
            n += len(chunk)
    return h.hexdigest(), n


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _take_lock(root: Path) -> int | None:
    if fcntl is None:
        return None
    fd = os.open(root / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise CatalogError(f"catalogue {root} is open for writing by another process "
                           f"(single writer; {LOCK_NAME} is locked)") from None
    return fd


def _release_lock(fd: int | None) -> None:
    if fd is not None:
        os.close(fd)
