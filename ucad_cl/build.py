"""``ucad-index build``: a library of meshes -> the part-labelled catalogue.

``build(library, catalog, options)`` discovers meshes, skips those already catalogued with the
same content key and options hash, runs the per-mesh pipeline (ingest -> filter -> render ->
filter by views -> edges -> segment -> classify -> features) in worker processes, and commits
each mesh atomically from the driver, the catalogue's single writer.

Untrusted libraries (decisions; reason codes in ``ucad_cl/reasons.py``)
* The driver never opens a mesh file: discovery and the "unchanged" test use ``stat`` only
  (path, size, mtime against the last commit of that path). Reading, hashing (the content key,
  ``ingest.mesh_identity``: format + bytes) and parsing happen in a worker, under its timeout and
  memory limit. A worker skips a new or changed path whose content is already catalogued with
  these options (a read-only look at the catalogue, no lock).
* Per-worker memory limit (``memory_limit_mb``, default half the machine's memory divided by the
  workers, at least 1 GiB): the worker runs under ``RLIMIT_DATA`` = limit + 1 GiB (an allocation
  past it raises ``MemoryError`` or kills the worker at once) and the driver polls each worker's
  resident memory every 0.1 s and kills a worker above the limit. Measured in
  ``bench/hostile.py``: after OpenCL is set up a worker's data segment is ~350-500 MB larger than
  its resident set, hence the headroom.
* Failures of a worker (it crashed, went over its memory limit, timed out, or was killed from
  outside) are attributed before anything is recorded. The meshes it had started are retried
  alone in a worker ("solo"); a crash or memory overrun while the worker held one mesh alone is
  recorded (``loader_crashed`` / ``too_large``). A timeout (no progress for ``timeout`` s) is
  retried once alone with twice the time, then recorded (``timeout``): a file that hangs the
  loader twice would otherwise stop every build forever, while a pause of the machine or a
  stopped worker costs one retry. A worker killed from outside (SIGKILL, SIGTERM: the OOM
  killer, a user) is an environment fault: its meshes are retried, and a mesh held by three
  killed workers stops the build (``worker_killed``), recording nothing.
* Environment faults (``disk_full``, ``io_error`` on the catalogue or staging side,
  ``worker_killed``) raise ``BuildStopped``: workers are stopped, nothing is recorded for the
  meshes in flight, and the message says what to free or fix; the next run continues.
* ``retry_failed``: reason codes whose recorded rejections are re-processed even though the file
  and options are unchanged (default for the CLI flag without codes: ``reasons.default_retry()``).

Engines
* ``local`` (default): ``workers`` processes, each with its own OpenCL context and
  ``cores // workers`` PoCL threads (no oversubscription). Inside a worker a loader thread
  prefetches (ingests) the next mesh while the current one is on the OpenCL device. Workers are
  replaced after ``recycle_after`` meshes so memory stays flat.
* ``ray``: the same per-mesh function as Ray tasks on an existing cluster (``ucad_cl.engines``).

Resumability: a mesh is either fully committed (rows + artifacts) or absent, so a build killed at
any moment (even SIGKILL) and run again continues where it stopped, with nothing duplicated.
A changed file (new content key) is re-processed and replaces the old entry; a change of any
option that affects results changes the options hash, and every mesh with another options hash
is re-processed (its entry replaced in one transaction).

Memory figures: ``BuildSummary.peak_rss_mb`` is the whole process tree (driver + workers,
resident memory summed, sampled every 0.1 s while workers run); ``peak_driver_mb`` the driver's
own peak (``ru_maxrss``); ``peak_worker_mb`` the largest worker peak (``VmHWM``).
"""
from __future__ import annotations

import errno
import gzip
import hashlib
import io
import json
import os
import queue
import shutil
import signal
import sqlite3
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from . import reasons
from .ingest import SUPPORTED_SUFFIXES, Budgets

CODE_VERSION = "3"        # bump when a change alters results: it enters the options hash


@dataclass(frozen=True)
class BuildOptions:
    """Everything that affects what is stored. Angles in degrees, sizes in pixels."""

    azimuth_step: float = 5.0
    elevations: tuple[float, ...] = (15.0,)
    fov_deg: float = 40.0
    size: int = 256
    segmenter: str = "prior"            # 'prior' | 'masks:DIR' | 'onnx:MODEL:CONFIG'
    threshold: float = 0.5              # part score threshold (UrbanCAD: 0.5)
    min_materials: int = 2
    max_triangles: int = 2_000_000      # reject above this (after decimation, if any)
    triangle_budget: int = 0            # decimate above this many triangles (0 = never)
    dominant_fraction: float = 0.97     # reject when one material covers this share of pixels
    min_visible_materials: int = 2
    features: bool = True
    edges: bool = True
    max_input_triangles: int = Budgets.max_triangles   # ingest budget, before allocation

    def to_dict(self) -> dict:
        d = asdict(self)
        d["elevations"] = list(self.elevations)
        return d

    def hash(self) -> str:
        blob = json.dumps({"code": CODE_VERSION, **self.to_dict()}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()

    def budgets(self) -> Budgets:
        """Ingest budgets: triangles as given, vertices three per triangle (at least the
        default vertex budget: files often carry unreferenced vertices)."""
        return Budgets(max_triangles=self.max_input_triangles,
                       max_vertices=max(Budgets.max_vertices, 3 * self.max_input_triangles))


@dataclass
class MeshRef:
    """A library file: path, size in bytes, mtime (s); size -1 when it cannot be stat-ed."""

    path: str
    size: int
    mtime: float


@dataclass
class BuildSummary:
    run_id: int
    discovered: int = 0
    skipped: int = 0
    accepted: int = 0
    rejected: int = 0
    failed: int = 0                     # rejections with an internal-error code (pipeline_error)
    retried: int = 0                    # attempts repeated after a worker failure
    seconds: float = 0.0
    reasons: dict = field(default_factory=dict)
    stage_seconds: dict = field(default_factory=dict)
    peak_rss_mb: float = 0.0            # process tree (driver + workers)
    peak_driver_mb: float = 0.0
    peak_worker_mb: float = 0.0
    memory_limit_mb: float = 0.0
    superseded_mb: float = 0.0          # objects replaced in this run, reclaimed by gc

    @property
    def processed(self) -> int:
        return self.accepted + self.rejected

    @property
    def meshes_per_s(self) -> float:
        return self.processed / self.seconds if self.seconds > 0 else 0.0


class BuildStopped(RuntimeError):
    """An environment fault stopped the build (nothing recorded for the meshes in flight).
    ``code`` is an environment reason code, ``str`` says what to free or fix; ``summary`` holds
    what the run did before it stopped."""

    def __init__(self, code: str, message: str, summary: BuildSummary | None = None):
        self.code = reasons.check(code, reasons.ENVIRONMENT)
        self.summary = summary
        super().__init__(message)


def environment_code(exc: BaseException) -> str | None:
    """The environment reason code of an error raised while writing the catalogue or staging
    files (``disk_full``, ``io_error``), or None when it is not an environment fault."""
    if isinstance(exc, OSError):
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return "disk_full"
        if exc.errno in (errno.EIO, errno.EROFS, errno.ENXIO, errno.ENODEV, errno.ESTALE):
            return "io_error"
        return None
    if isinstance(exc, sqlite3.Error):
        code = getattr(exc, "sqlite_errorcode", None)
        text = str(exc).lower()
        if code == 13 or "disk is full" in text:                 # SQLITE_FULL
            return "disk_full"
        if (code is not None and code & 0xFF in (8, 10, 14)) or "disk i/o error" in text:
            return "io_error"                                   # READONLY, IOERR, CANTOPEN
    return None


def printable(text: str) -> str:
    """``text`` as valid UTF-8 for logs and terminals: bytes of a non-UTF-8 file name (Python's
    surrogate escapes) are written ``\\xNN``."""
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def default_memory_limit_mb(workers: int) -> float:
    """Half the machine's memory divided among the workers, at least 1 GiB each."""
    try:
        import psutil
        total = psutil.virtual_memory().total
    except ImportError:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return max(1024.0, total / 2**20 / 2 / max(1, workers))


# ----------------------------------------------------------------------------- discovery

def discover(library: str | os.PathLike, *, uids: Iterable[str] | None = None,
             log=None) -> list[MeshRef]:
    """Mesh files of a library, sorted by path.

    ``library`` is a folder tree (every entry with a supported suffix that is not a directory:
    FIFOs, devices, dangling symlinks and symlink loops included, so each is recorded with its
    reason; hidden names are skipped; symlinked folders are not followed), or a manifest file
    (.txt: one path per line; .json: a list of paths or ``{"paths": [...]}``), paths relative to
    the manifest's folder. ``uids`` keeps only files whose stem is in it (e.g. Objaverse uids of
    vehicle categories). Only ``stat`` is used: nothing is opened. ``log`` gets a line for each
    folder that cannot be listed.
    """
    root = Path(library)
    if not root.exists():
        raise FileNotFoundError(f"library {root} does not exist")
    if root.is_dir():
        paths = []

        def unlistable(err):
            if log is not None:
                log(f"warning: cannot list {printable(str(err.filename))}: {err.strerror}")

        for folder, dirs, files in os.walk(root, onerror=unlistable):
            dirs[:] = [d for d in dirs if not d.startswith(".")]
            paths += [Path(folder) / f for f in files
                      if Path(f).suffix.lower() in SUPPORTED_SUFFIXES and not f.startswith(".")]
    else:
        paths = _manifest_paths(root)
    if uids is not None:
        keep = set(uids)
        paths = [p for p in paths if p.stem in keep]
    refs = []
    for p in sorted(set(paths)):
        try:
            st = p.stat()
        except OSError:                                 # a symlink loop / dangling link: the
            try:                                        # link's own stat, so it stays "unchanged"
                st = p.lstat()
            except OSError:
                refs.append(MeshRef(str(p), -1, 0.0))   # recorded with its reason by a worker
                continue
        refs.append(MeshRef(str(p), st.st_size, st.st_mtime))
    return refs


def _manifest_paths(manifest: Path) -> list[Path]:
    """Paths listed by a .txt / .json manifest (ValueError naming the manifest and the problem)."""
    try:
        text = manifest.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"manifest {printable(str(manifest))} is not UTF-8 text ({e.reason} at "
                         f"byte {e.start})") from None
    if manifest.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as e:
            raise ValueError(f"manifest {printable(str(manifest))} is not valid JSON: {e}"
                             ) from None
        items = data.get("paths", []) if isinstance(data, dict) else data
        if not isinstance(items, list):
            raise ValueError(f"manifest {printable(str(manifest))}: expected a list of paths or "
                             '{"paths": [...]}')
    else:
        items = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    for k, p in enumerate(items):
        if not isinstance(p, str) or not p or "\0" in p:
            raise ValueError(f"manifest {printable(str(manifest))}: entry {k} ({str(p)[:60]!r}) "
                             "is not a path")
    return [(manifest.parent / p) if not Path(p).is_absolute() else Path(p) for p in items]


def read_uid_list(path: str | os.PathLike, categories: Iterable[str] | None = None) -> list[str]:
    """Uids from a text file (one per line) or an Objaverse-style annotations JSON
    (``{uid: {"name", "categories": [{"name": ...}], "tags": [{"name": ...}], ...}}``: its keys).
    ``categories`` keeps only annotated uids with a category or tag of one of these names
    (case-insensitive), e.g. ``("car", "vehicle", "truck")``."""
    p = Path(path)
    if p.suffix.lower() != ".json":
        if categories:
            raise ValueError(f"{p}: --categories needs an annotations JSON, not a uid list")
        return [ln.strip() for ln in p.read_text(encoding="utf-8").splitlines() if ln.strip()]
    data = json.loads(p.read_text(encoding="utf-8"))
    if not isinstance(data, dict):
        if categories:
            raise ValueError(f"{p}: --categories needs annotations ({{uid: {{...}}}}), got a list")
        return [str(u) for u in data]
    if not categories:
        return list(data.keys())
    want = {c.strip().lower() for c in categories}

    def names(items):
        for it in items or []:
            yield (it.get("name", "") if isinstance(it, dict) else str(it)).lower()

    return [uid for uid, ann in data.items() if isinstance(ann, dict)
            and want & set(names(ann.get("categories"))) | want & set(names(ann.get("tags")))]


def content_sha256(path: str | os.PathLike) -> str:
    """The mesh key (``ingest.mesh_identity``: format tag + the bytes of the file and of the
    files it references); for a file that cannot be read, ``ingest.unreadable_identity``."""
    from .ingest import IngestError, mesh_identity, unreadable_identity

    try:
        return mesh_identity(path)
    except IngestError:
        return unreadable_identity(path)


# ----------------------------------------------------------------------------- per mesh

@dataclass
class Skipped:
    """A worker's answer for a path whose content is already catalogued with these options."""

    sha256: str


class Pipeline:
    """The per-mesh stages with their state (segmenter, feature extractor) built once."""

    def __init__(self, options: BuildOptions):
        from .cameras import make_ring

        self.options = options
        self.budgets = options.budgets()
        self.ring = make_ring(azimuth_step=options.azimuth_step, elevations=options.elevations,
                              fov_deg=options.fov_deg, size=options.size)
        self.segmenter = make_segmenter(options.segmenter)
        self.extractor = None
        if options.features:
            from .features import HogExtractor
            self.extractor = HogExtractor()

    def identify(self, ref: MeshRef) -> tuple[str, object]:
        """(content key, None), or (key, rejected CatalogEntry) when the file cannot be read."""
        from .ingest import IngestError, mesh_identity, unreadable_identity

        try:
            return mesh_identity(ref.path, self.budgets), None
        except IngestError as exc:
            sha = unreadable_identity(ref.path)
            return sha, rejected_entry(ref, sha, exc.reason, str(exc))

    def load(self, ref: MeshRef):
        """Ingest (may raise IngestError or MemoryError). Returns (mesh, seconds)."""
        from .ingest import load_mesh

        t0 = time.perf_counter()
        _inject_fault(ref.path)
        mesh = load_mesh(ref.path, budgets=self.budgets)
        return mesh, time.perf_counter() - t0

    def load_entry(self, ref: MeshRef, sha: str):
        """``load`` with every input fault turned into a rejected entry: (mesh, secs, None) or
        (None, 0, entry). MemoryError passes through (the caller attributes it)."""
        from .ingest import IngestError, describe_exception

        try:
            mesh, secs = self.load(ref)
            return mesh, secs, None
        except IngestError as exc:
            return None, 0.0, rejected_entry(ref, sha, exc.reason, str(exc))
        except MemoryError:
            raise
        except Exception as exc:             # a reader quirk on a strange file: an input fault
            return None, 0.0, rejected_entry(ref, sha, "unreadable",
                                             f"{ref.path}: {describe_exception(exc)}")

    def process(self, ref: MeshRef, mesh, load_seconds: float, staging: Path):
        """Everything after ingest; returns a CatalogEntry (accepted or rejected)."""
        from ucad_catalog.entry import CatalogEntry
        from ucad_catalog.exr import write_viewset_exr

        from .filter import filter_mesh, filter_views
        from .artifacts import Verdict

        o = self.options
        timings = {"ingest": load_seconds}
        t = time.perf_counter()
        notes = "; ".join(mesh.report.notes)

        def lap(name):
            nonlocal t
            now = time.perf_counter()
            timings[name] = timings.get(name, 0.0) + now - t
            t = now

        def rejected(verdict):
            if notes:
                verdict = Verdict(False, verdict.reason, f"{verdict.detail} ({notes})")
            return CatalogEntry.from_results(sha256=mesh.sha256, path=ref.path, size=ref.size,
                                             mtime=ref.mtime, verdict=verdict, mesh=mesh,
                                             timings=timings)

        if o.triangle_budget and mesh.n_faces > o.triangle_budget:
            from .decimate import decimate
            mesh = decimate(mesh, o.triangle_budget)
            lap("decimate")
        verdict = filter_mesh(mesh, min_materials=o.min_materials, max_triangles=o.max_triangles)
        lap("filter")
        if not verdict.accepted:
            return rejected(verdict)
        from .render import render_views
        views = render_views(mesh, self.ring)
        lap("render")
        verdict = filter_views(mesh, views, dominant_fraction=o.dominant_fraction,
                               min_visible_materials=o.min_visible_materials)
        lap("filter")
        if not verdict.accepted:
            return rejected(verdict)
        artifacts = {}
        staging.mkdir(parents=True, exist_ok=True)
        exr = staging / f"{mesh.sha256}.views.exr"
        write_viewset_exr(exr, views, mesh)
        artifacts["views.exr"] = exr
        lap("write")
        if o.edges:
            from .edges import material_edges
            edges = material_edges(views).edges
            artifacts["edges.npy.gz"] = npy_gz_bytes(np.packbits(edges > 0, axis=-1))
            lap("edges")
        masks = self.segmenter.segment(mesh, views)
        lap("segment")
        from .classify import classify_parts
        from .segment import name_priors
        table = classify_parts(mesh, views, masks, threshold=o.threshold, priors=name_priors(mesh))
        lap("classify")
        if self.extractor is not None:
            from .features import view_features
            from .shade import shade_views
            images = shade_views(mesh, views, background=(128, 128, 128))
            feats = view_features(self.extractor, images, views).feats
            artifacts["features.npy"] = npy_bytes(feats.astype(np.float32))
            lap("features")
        artifacts["parts.png"] = parts_sheet_png(views, table)
        lap("write")
        from .pose import _box_side
        visible = views.material_counts()[:, 1:].sum(axis=1)
        view_stats = [{"visible_pixels": int(visible[v]),
                       "box_side": float(_box_side(views.mat_id[v] > 0))}
                      for v in range(views.n_views)]
        return CatalogEntry.from_results(
            sha256=mesh.sha256, path=ref.path, size=ref.size, mtime=ref.mtime,
            verdict=Verdict(True, "", notes), mesh=mesh, table=table, ring=self.ring,
            artifacts=artifacts, timings=timings, view_stats=view_stats)

    def process_entry(self, ref: MeshRef, mesh, load_seconds: float, staging: Path):
        """``process`` with an unexpected error recorded as ``pipeline_error``. Environment
        faults (``environment_code``) and MemoryError pass through."""
        from .ingest import describe_exception

        try:
            return self.process(ref, mesh, load_seconds, staging)
        except MemoryError:
            raise
        except Exception as exc:
            if environment_code(exc):
                raise
            return rejected_entry(ref, mesh.sha256, "pipeline_error",
                                  f"{ref.path}: {describe_exception(exc)}")


class KnownContent:
    """Read-only question to the catalogue, asked by workers: is content ``sha`` already
    catalogued with options hash ``ohash`` (and not with a reason being retried)? No lock; any
    error answers "no" (the mesh is then simply processed)."""

    def __init__(self, catalog: str | os.PathLike | None, ohash: str | None,
                 retry: Iterable[str] = ()):
        self._db = Path(catalog) / "catalog.sqlite" if catalog else None
        self._ohash, self._retry = ohash, set(retry)
        self._conn = None

    def __call__(self, sha: str) -> bool:
        if self._db is None or not self._ohash:
            return False
        try:
            if self._conn is None:
                self._conn = sqlite3.connect(f"{self._db.resolve().as_uri()}?mode=ro", uri=True,
                                             timeout=5.0, check_same_thread=False)
            row = self._conn.execute("SELECT state, reason FROM meshes WHERE sha256=? AND "
                                     "options_hash=?", (sha, self._ohash)).fetchone()
        except sqlite3.Error:
            return False
        return row is not None and not (row[0] == "rejected" and row[1] in self._retry)


def _inject_fault(path: str) -> None:
    """Test hook standing in for a native loader that crashes or hangs on a broken file:
    ``UCAD_FAULT_INJECT="crash:NAME,hang:NAME"`` segfaults / hangs while loading a path that
    contains NAME. Unset in normal use."""
    spec = os.environ.get("UCAD_FAULT_INJECT")
    if not spec:
        return
    for item in spec.split(","):
        kind, _, needle = item.partition(":")
        if needle and needle in path:
            if kind == "crash":               # a real fault: LLVM (PoCL) catches kill(SIGSEGV)
                import ctypes
                ctypes.string_at(0)
            elif kind == "hang":
                time.sleep(3600)


def make_segmenter(spec: str):
    """'prior' | 'masks:DIR' | 'onnx:MODEL:CONFIG.json' -> a Segmenter (``segment.make_segmenter``)."""
    from .segment import make_segmenter as factory

    kind, _, arg = spec.partition(":")
    model, _, config = arg.partition(":") if kind == "onnx" else (arg, "", "")
    return factory(kind, model or None, config or None)


def rejected_entry(ref: MeshRef, sha: str, reason: str, detail: str):
    from ucad_catalog.entry import CatalogEntry
    from .artifacts import Verdict

    reasons.check(reason, reasons.REJECTION)
    return CatalogEntry.from_results(sha256=sha, path=ref.path, size=max(ref.size, 0),
                                     mtime=ref.mtime, verdict=Verdict(False, reason, detail))


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def npy_gz_bytes(a: np.ndarray) -> bytes:
    """Deterministic gzip (mtime 0) of an .npy file. Level 1: a mesh's packed edge maps in 2 ms
    (56 kB) instead of 6 ms (44 kB) at level 6."""
    return gzip.compress(npy_bytes(a), compresslevel=1, mtime=0)


def parts_sheet_png(views, table) -> bytes:
    """Contact sheet of (at most 24 of) the views coloured by part, as PNG bytes."""
    import cv2

    from .sheets import part_sheet

    sub = views.select(np.arange(0, views.n_views, max(1, views.n_views // 24)))
    ok, png = cv2.imencode(".png", np.ascontiguousarray(part_sheet(sub, table, 1600)[..., ::-1]))
    return png.tobytes()


# ----------------------------------------------------------------------------- driver

def build(library: str | os.PathLike, catalog: str | os.PathLike,
          options: BuildOptions = BuildOptions(), *, workers: int = 1, engine: str = "local",
          timeout: float = 600.0, recycle_after: int = 200, progress: bool = True,
          uids: Iterable[str] | None = None, limit: int | None = None,
          ray_address: str | None = None, log=print, retry_failed: Iterable[str] | None = None,
          memory_limit_mb: float | None = None) -> BuildSummary:
    """Build or update the catalogue at ``catalog`` from ``library``. See the module docstring.

    Raises ``BuildStopped`` on an environment fault (the summary of what was done is attached),
    ``ucad_catalog.CatalogError`` when the catalogue cannot be opened (another writer holds it,
    not a catalogue), ValueError / FileNotFoundError for bad arguments or a missing library.
    """
    import resource

    from ucad_catalog.store import Catalog

    t_start = time.perf_counter()
    make_segmenter(options.segmenter)     # a bad --segmenter fails here, not in every worker
    retry = tuple(reasons.check(r, reasons.REJECTION) for r in (retry_failed or ()))
    if memory_limit_mb is None:
        memory_limit_mb = default_memory_limit_mb(workers)
    if not memory_limit_mb > 0:
        raise ValueError(f"memory_limit_mb must be > 0, got {memory_limit_mb}")
    refs = discover(library, uids=uids, log=log)
    if limit:
        refs = refs[:limit]
    summary = BuildSummary(run_id=0, discovered=len(refs), memory_limit_mb=memory_limit_mb)
    cat = staging = runlog = None
    todo: list[tuple[MeshRef, bool]] = []
    worker_skips = [0]                                # skips decided by workers (content known)
    try:
        cat = _catalogue_step(lambda: Catalog.open(catalog, create=True), catalog)
        run_id = _catalogue_step(lambda: cat.begin_run({**options.to_dict(), "code": CODE_VERSION},
                                                       engine), catalog)
        summary.run_id = run_id
        ohash = cat.run_options_hash
        for ref in refs:
            rec = cat.file_record(ref.path)
            if rec and rec[1] == ref.size and rec[2] == ref.mtime:
                verdict = cat.mesh_verdict(rec[0])          # unchanged file: no need to re-hash
                if verdict is None or verdict[2] != ohash:
                    todo.append((ref, False))
                elif verdict[0] == "rejected" and verdict[1] in retry:
                    todo.append((ref, True))
                else:
                    summary.skipped += 1
            else:
                todo.append((ref, False))                   # new or changed: a worker decides
        log(f"{len(refs)} meshes found, {summary.skipped} unchanged (skipped), "
            f"{len(todo)} to process with the {engine} engine")
        runlog = RunLog(Path(catalog) / "logs" / f"run-{run_id:05d}.log")
        runlog.write(f"run {run_id} engine={engine} workers={workers} found={len(refs)} "
                     f"skipped={summary.skipped} todo={len(todo)} memory_limit_mb="
                     f"{memory_limit_mb:.0f} retry={list(retry)} options={options.to_dict()}")

        def commit(entry):
            try:
                cat.commit_mesh(entry, move_files=True)
            except (OSError, sqlite3.Error) as exc:
                code = environment_code(exc)
                if code is None:
                    raise
                raise BuildStopped(code, f"storing {printable(entry.path)}: "
                                         f"{type(exc).__name__}: {exc}") from None
            n = summary.processed + 1
            runlog.write(f"{n}/{len(todo)} {entry.state} {printable(entry.path)}"
                         + (f" reason={entry.reason}: {printable(entry.detail)}"
                            if entry.reason else "")
                         + f" s={sum((entry.timings or {}).values()):.2f}"
                         + (f" rss_mb={_tree_rss_mb():.0f}" if n % 50 == 0 else ""))
            if entry.state == "accepted":
                summary.accepted += 1
            else:
                summary.rejected += 1
                summary.reasons[entry.reason] = summary.reasons.get(entry.reason, 0) + 1
                summary.failed += entry.reason == "pipeline_error"
            for k, v in (entry.timings or {}).items():
                summary.stage_seconds[k] = summary.stage_seconds.get(k, 0.0) + v

        def skip(ref, sha):
            summary.skipped += 1
            worker_skips[0] += 1
            runlog.write(f"skipped {printable(ref.path)}: content {sha[:12]} already catalogued")

        staging = Path(catalog) / "staging"
        shutil.rmtree(staging, ignore_errors=True)      # a killed run's leftovers (we hold the lock)
        known = (str(catalog), ohash, retry)
        if engine == "local":
            _run_local(todo, options, commit, skip, workers=workers, timeout=timeout,
                       recycle_after=recycle_after, progress=progress, staging=staging, log=log,
                       known=known, memory_limit_mb=memory_limit_mb, summary=summary,
                       runlog=runlog)
        elif engine == "ray":
            from .engines import run_ray
            run_ray(todo, options, commit, address=ray_address, progress=progress,
                    staging=staging, log=log, timeout=timeout,
                    num_cpus=None if ray_address else workers, on_skip=skip, known=known,
                    summary=summary)
        else:
            raise ValueError(f"unknown engine {engine!r}: use local or ray")
        shutil.rmtree(staging, ignore_errors=True)
        _finish_summary(summary, t_start, resource)
        summary.superseded_mb = cat.superseded_bytes / 2**20
        _catalogue_step(lambda: cat.finish_run(run_id, {
            "skipped": summary.skipped, "failed": summary.failed, "retried": summary.retried,
            "meshes_per_s": summary.meshes_per_s, "stage_seconds": summary.stage_seconds,
            "peak_rss_mb": summary.peak_rss_mb}), catalog)
        runlog.write(f"finished: {summary.accepted} accepted, {summary.rejected} rejected "
                     f"{summary.reasons}, {summary.skipped} skipped, {summary.retried} retried, "
                     f"{summary.meshes_per_s:.2f} meshes/s, peak memory {summary.peak_rss_mb:.0f}"
                     f" MB (process tree), driver {summary.peak_driver_mb:.0f} MB, largest "
                     f"worker {summary.peak_worker_mb:.0f} MB")
    except BuildStopped as stop:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
        _finish_summary(summary, t_start, resource)
        left = len(todo) - summary.processed - worker_skips[0]
        message = _stop_message(stop.code, str(stop), catalog, summary, max(left, 0))
        if runlog is not None:
            runlog.write(f"stopped [{stop.code}]: {message}")
        if cat is not None and summary.run_id:
            try:                                    # best effort: the disk may still be full
                cat.finish_run(summary.run_id, {"skipped": summary.skipped,
                                                "stopped": stop.code})
            except (OSError, sqlite3.Error):
                pass
        raise BuildStopped(stop.code, message, summary) from None
    finally:
        if runlog is not None:
            runlog.close()
        if cat is not None:
            cat.close()
    return summary


def _catalogue_step(fn, catalog):
    """Run a catalogue call, turning an environment fault into BuildStopped."""
    try:
        return fn()
    except (OSError, sqlite3.Error) as exc:
        code = environment_code(exc)
        if code is None:
            raise
        raise BuildStopped(code, f"catalogue {printable(str(catalog))}: {type(exc).__name__}: "
                                 f"{exc}") from None


def _finish_summary(summary: BuildSummary, t_start: float, resource) -> None:
    summary.seconds = time.perf_counter() - t_start
    summary.peak_driver_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    summary.peak_rss_mb = max(summary.peak_rss_mb, summary.peak_driver_mb)


def _stop_message(code: str, detail: str, catalog, summary: BuildSummary, left: int) -> str:
    """What stopped the build and what to do about it (one paragraph for the terminal)."""
    cat = printable(str(catalog))
    done = (f"{summary.processed} meshes were committed in this run and {left} remain; nothing "
            "was recorded for the meshes in flight. Run the same command again to continue.")
    if code == "disk_full":
        try:
            free = f"{shutil.disk_usage(catalog).free / 2**20:.1f} MiB free"
        except OSError:
            free = "free space unknown"
        return (f"build stopped: no space left on the file system of the catalogue {cat} "
                f"({free}) - {detail}. Free space there (`ucad-index gc --catalog {cat}` "
                f"deletes unreferenced objects). {done}")
    if code == "io_error":
        return (f"build stopped: I/O error on the file system of the catalogue {cat} - "
                f"{detail}. Check the disk (dmesg), then `ucad-index verify --catalog {cat}`. "
                f"{done}")
    if code == "worker_killed":
        return (f"build stopped: {detail}. Something kills ucad workers - most often the "
                "kernel's OOM killer (check `dmesg | grep -i oom`): lower --workers or "
                f"--memory-limit-mb. {done}")
    if code == "worker_start_failed":
        return (f"build stopped: {detail}. Check `ucad-index info` (OpenCL) and that "
                f"--memory-limit-mb leaves room for a worker to start. {done}")
    return f"build stopped [{code}]: {detail}. {done}"


class RunLog:
    """Append-only, line-buffered log of one run (``CATALOG/logs/run-NNNNN.log``): every commit
    with its reason and seconds, process-tree memory every 50 meshes, worker failures and
    retries. Flushed per line, so a killed run still says how far it got and why. A full disk
    silences it (the build reports that itself)."""

    def __init__(self, path: Path):
        self._f = None
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(path, "a", buffering=1, encoding="utf-8", errors="backslashreplace")
        except OSError:
            pass

    def write(self, line: str) -> None:
        if self._f is None:
            return
        try:
            self._f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {line}\n")
        except OSError:
            self._f = None

    def close(self) -> None:
        if self._f is not None:
            try:
                self._f.close()
            except OSError:
                pass
            self._f = None


def _tree_rss_mb() -> float:
    """Resident memory of this process and its children (MB); 0 without psutil."""
    try:
        import psutil
    except ImportError:
        return 0.0
    total = 0
    try:
        me = psutil.Process()
        for p in [me] + me.children(recursive=True):
            try:
                total += p.memory_info().rss
            except psutil.Error:
                pass
    except psutil.Error:
        return 0.0
    return total / 2**20


def _proc_memory_mb(pid: int) -> tuple[float, float, float]:
    """(VmRSS, VmHWM, VmData) of a process in MB from /proc; zeros where unavailable."""
    out = {"VmRSS": 0.0, "VmHWM": 0.0, "VmData": 0.0}
    try:
        with open(f"/proc/{pid}/status", "rb") as f:
            for line in f:
                key, _, value = line.partition(b":")
                k = key.decode()
                if k in out:
                    out[k] = int(value.split()[0]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return out["VmRSS"], out["VmHWM"], out["VmData"]


# ----------------------------------------------------------------------------- local engine

EXIT_MEMORY = 86                 # a worker that hit MemoryError exits with this status
DATA_HEADROOM_MB = 1024          # RLIMIT_DATA = memory limit + this (see module doc)
_CRASH_SIGNALS = {signal.SIGSEGV, signal.SIGBUS, signal.SIGILL, signal.SIGFPE, signal.SIGABRT,
                  signal.SIGSYS, signal.SIGTRAP}
_POLL_S = 0.1                    # driver loop: queue wait and memory sampling period
_MAX_STARTS_FAILED = 3
_MAX_KILLS = 3


def _worker_main(wid: int, task_q, conn, state, options_dict: dict, threads: int,
                 staging: str, known: tuple, memory_limit_mb: float) -> None:
    """Worker process: prefetching loader thread + OpenCL stages. Messages to the driver:
    ('ready', wid), then per task index i: ('loading' | 'loaded' | 'processing', wid, i),
    ('identity', wid, i, sha), ('done', wid, i, entry), ('skip', wid, i, sha), ('env', wid, i, code, detail), or
    ('memory', wid, i, detail) after which the worker exits with EXIT_MEMORY.
    ``state`` (shared memory, written before each step, so it survives a crash of this process):
    [index being loaded, index being processed], -1 for none. Messages go through this worker's
    own pipe (``conn``): a worker that dies mid-message cannot block the others, as it could
    while holding the lock of a queue they share."""
    send_lock = threading.Lock()

    class _Results:
        @staticmethod
        def put(msg):
            with send_lock:
                conn.send(msg)

    result_q = _Results()
    if memory_limit_mb:
        import resource
        limit = int((memory_limit_mb + DATA_HEADROOM_MB) * 2**20)
        _, hard = resource.getrlimit(resource.RLIMIT_DATA)
        if hard == resource.RLIM_INFINITY or hard > limit:
            resource.setrlimit(resource.RLIMIT_DATA, (limit, hard))
    os.environ["POCL_MAX_PTHREAD_COUNT"] = str(threads)
    os.environ["POCL_CPU_MAX_CU_NUM"] = str(threads)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    opts = BuildOptions(**{**options_dict, "elevations": tuple(options_dict["elevations"])})
    pipe = Pipeline(opts)
    is_known = KnownContent(*known)
    loaded: queue.Queue = queue.Queue(maxsize=1)
    parent = os.getppid()
    result_q.put(("ready", wid))

    def get(q):
        """Blocking get that ends the worker when the driver is gone (e.g. killed with -9)."""
        while True:
            try:
                return q.get(timeout=1.0)
            except queue.Empty:
                if os.getppid() != parent:
                    os._exit(0)

    def memory_fault(i, where):
        result_q.put(("memory", wid, i, f"MemoryError while {where}"))   # written: synchronous
        os._exit(EXIT_MEMORY)

    def load_one(i, ref, force):
        from .ingest import describe_exception, unreadable_identity
        try:
            sha, entry = pipe.identify(ref)
            result_q.put(("identity", wid, i, sha))
            if entry is None and not force and is_known(sha):
                return (i, ref, None, 0.0, Skipped(sha))
            if entry is None:
                mesh, secs, entry = pipe.load_entry(ref, sha)
                return (i, ref, mesh, secs, entry)
            return (i, ref, None, 0.0, entry)
        except MemoryError:
            memory_fault(i, "loading")
        except Exception as exc:                    # a bug in our checks: still a verdict
            return (i, ref, None, 0.0, rejected_entry(ref, unreadable_identity(ref.path),
                                                      "unreadable", describe_exception(exc)))

    def loader():
        while True:
            item = get(task_q)
            if item is None:
                loaded.put(None)
                return
            i, ref, force = item
            state[0] = i
            result_q.put(("loading", wid, i))
            out = load_one(i, ref, force)
            state[0] = -1
            result_q.put(("loaded", wid, i))
            loaded.put(out)

    threading.Thread(target=loader, daemon=True).start()
    stage_dir = Path(staging) / f"w{os.getpid()}"
    while True:
        item = get(loaded)
        if item is None:
            return
        i, ref, mesh, secs, result = item
        item = None
        state[1] = i
        result_q.put(("processing", wid, i))
        if mesh is None:
            msg = (("skip", wid, i, result.sha256) if isinstance(result, Skipped)
                   else ("done", wid, i, result))
        else:
            try:
                msg = ("done", wid, i, pipe.process_entry(ref, mesh, secs, stage_dir))
            except MemoryError:
                mesh = None
                memory_fault(i, "processing")
            except Exception as exc:                 # process_entry lets only these through
                msg = ("env", wid, i, environment_code(exc), f"{type(exc).__name__}: {exc}")
            mesh = None
        state[1] = -1
        result_q.put(msg)


class _Worker:
    def __init__(self, wid, ctx, args):
        self.wid = wid
        self.task_q = ctx.Queue()
        self.state = ctx.Array("q", [-1, -1], lock=False)
        self.conn, child = ctx.Pipe(duplex=False)     # results: this worker's own pipe
        self.proc = ctx.Process(target=_worker_main, daemon=True,
                                args=(wid, self.task_q, child, self.state, *args))
        self.proc.start()
        child.close()                                 # EOF on self.conn once the worker is gone
        self.assigned: list[int] = []          # task indices sent, in order
        self.started: set[int] = set()         # indices whose loading began
        self.ready = False
        self.born = self.since = time.monotonic()
        self.peak_mb = self.data_mb = 0.0

    def send(self, i, ref, force):
        self.assigned.append(i)
        self.task_q.put((i, ref, force))

    def stop(self, kill=False):
        if kill:
            self.proc.kill()
        else:
            self.task_q.put(None)
        self.proc.join(timeout=10)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()
        self.task_q.cancel_join_thread()
        self.conn.close()


def _run_local(todo, options, commit, skip, *, workers, timeout, recycle_after, progress,
               staging, log, known, memory_limit_mb, summary, runlog):
    import multiprocessing as mp

    from tqdm import tqdm

    if not todo:
        return
    ctx = mp.get_context("spawn")
    workers = max(1, min(workers, len(todo)))
    threads = max(1, (os.cpu_count() or 1) // workers)
    staging.mkdir(parents=True, exist_ok=True)
    args = (options.to_dict(), threads, str(staging), known, memory_limit_mb)
    next_wid = iter(range(1 << 30))
    pool = [_Worker(next(next_wid), ctx, args) for _ in range(workers)]
    pending = list(range(len(todo)))[::-1]          # stack: pop() gives the next index
    finished: set[int] = set()
    solo: set[int] = set()                          # run with no other mesh in the worker
    timed_out: set[int] = set()
    attempts: dict[int, int] = {}
    kills: dict[int, int] = {}
    starts_failed = 0
    startup_limit = max(300.0, timeout)
    bar = tqdm(total=len(todo), unit="mesh", desc="build", disable=not progress, smoothing=0.05)
    me = os.getpid()
    last_sample = 0.0

    def outstanding(w):
        return [i for i in w.assigned if i not in finished]

    def feed(w):
        # at most two tasks per worker: one on the device, one being prefetched; a worker takes
        # no more than recycle_after tasks in its life; a solo task waits for an idle worker
        while pending and len(outstanding(w)) < 2 and len(w.assigned) < recycle_after:
            if any(i in solo for i in outstanding(w)):
                return
            i = pending[-1]
            if i in solo and outstanding(w):
                return
            pending.pop()
            w.send(i, *todo[i])

    def finish(i, entry):
        finished.add(i)
        commit(entry)
        bar.update(1)

    def record(i, reason, detail):
        from .ingest import unreadable_identity
        ref = todo[i][0]
        sha = shas.get(i) or unreadable_identity(ref.path)
        log(f"rejected {printable(ref.path)}: {reason}: {detail}")
        finish(i, rejected_entry(ref, sha, reason, f"{ref.path}: {detail}"))

    def restart(w):
        nw = _Worker(next(next_wid), ctx, args)
        pool[pool.index(w)] = nw
        return nw

    def fail(w, event, detail):
        """Worker ``w`` failed (crash | memory | timeout | killed); see the module docstring."""
        nonlocal starts_failed
        sample(w)
        w.stop(kill=True)
        held = outstanding(w)
        if not w.ready:
            starts_failed += 1
            runlog.write(f"worker {w.wid} failed to start ({detail}), attempt {starts_failed}")
            if starts_failed >= _MAX_STARTS_FAILED:
                raise BuildStopped("worker_start_failed",
                                   f"a worker process failed to start {starts_failed} times "
                                   f"(last: {detail})")
        active = [i for i in held if i in w.started]
        if event == "crash":
            running = {w.state[0], w.state[1]} - {-1}
            active = [i for i in held if i in running] or active
        runlog.write(f"worker {w.wid} {event}: {detail}; held {[printable(todo[i][0].path) for i in held]}")
        for i in held:
            if i not in active:
                pending.append(i)                   # never started there: innocent
                continue
            attempts[i] = attempts.get(i, 0) + 1
            name = printable(todo[i][0].path)
            if event == "killed":
                kills[i] = kills.get(i, 0) + 1
                if kills[i] >= _MAX_KILLS:
                    raise BuildStopped("worker_killed",
                                       f"workers were killed from outside {kills[i]} times "
                                       f"while processing {name} (last: {detail})")
                pending.append(i)
            elif event == "timeout":
                if i in timed_out:
                    record(i, "timeout", f"no progress for {2 * timeout:.0f} s on this mesh, "
                                         f"alone in its worker, after a first timeout of "
                                         f"{timeout:.0f} s")
                    continue
                timed_out.add(i)
                solo.add(i)
                pending.append(i)
            elif len(active) == 1 or attempts[i] >= _MAX_KILLS:
                record(i, "too_large" if event == "memory" else "loader_crashed",
                       f"{detail} (the worker held only this mesh)" if len(active) == 1
                       else f"{detail} ({attempts[i]} attempts)")
                continue
            else:
                solo.add(i)
                pending.append(i)
            summary.retried += 1
            log(f"retrying {name} ({event}: {detail})")
        pending.sort(key=lambda k: (k not in solo, -k))   # pop(): in order, solo retries last
        restart(w)

    def sample(w):
        rss, hwm, data = _proc_memory_mb(w.proc.pid)
        w.peak_mb = max(w.peak_mb, hwm)
        w.data_mb = data or w.data_mb
        summary.peak_worker_mb = max(summary.peak_worker_mb, w.peak_mb)
        return rss

    def watch():
        """Sample memory (tree peak, worker peaks) and enforce the memory limit."""
        tree = _proc_memory_mb(me)[0]
        for w in list(pool):
            if not w.proc.is_alive():
                continue
            rss = sample(w)
            tree += rss
            if memory_limit_mb and rss > memory_limit_mb and outstanding(w):
                fail(w, "memory", f"worker resident memory {rss:.0f} MB exceeded the limit of "
                                  f"{memory_limit_mb:.0f} MB")
        summary.peak_rss_mb = max(summary.peak_rss_mb, tree)

    shas: dict[int, str] = {}

    def handle(msg):
        kind, wid = msg[0], msg[1]
        w = next((w for w in pool if w.wid == wid), None)
        if w is None:
            return                                      # from a worker already replaced
        w.since = time.monotonic()
        if kind == "ready":
            w.ready = True
            return
        i = msg[2]
        if i in finished or i not in w.assigned:
            return
        if kind == "loading":
            w.started.add(i)
        elif kind == "identity":
            shas[i] = msg[3]
        elif kind == "memory":
            fail(w, "memory", msg[3])
        elif kind == "env":
            raise BuildStopped(msg[3], f"{printable(todo[i][0].path)}: {msg[4]}")
        elif kind in ("done", "skip"):
            if kind == "done":
                finish(i, msg[3])
            else:
                finished.add(i)
                skip(todo[i][0], msg[3])
                bar.update(1)
            if len(w.assigned) >= recycle_after and not outstanding(w):
                w.stop()                                # recycle: memory stays flat
                restart(w)

    def drain(wait_s):
        """Handle every message waiting in the workers' pipes (waiting up to ``wait_s``)."""
        from multiprocessing.connection import wait

        while True:
            conns = {w.conn: w for w in pool if not w.conn.closed}
            ready = wait(list(conns), timeout=wait_s) if conns else []
            if not ready:
                return
            wait_s = 0
            for c in ready:
                w = conns[c]
                if w not in pool or c.closed:
                    continue
                try:
                    msg = c.recv()
                except (EOFError, OSError):             # gone: the liveness check handles it
                    c.close()
                    continue
                handle(msg)

    for w in pool:
        feed(w)
    try:
        while len(finished) < len(todo):
            drain(_POLL_S)
            now = time.monotonic()
            if now - last_sample >= _POLL_S:
                last_sample = now
                watch()
            for w in list(pool):
                if w not in pool:
                    continue
                if not w.proc.is_alive():
                    drain(0)                            # what it said before dying comes first
                    if w not in pool:
                        continue
                    if outstanding(w) or not w.ready:
                        fail(w, *_death(w, memory_limit_mb))
                    else:
                        restart(w)
                elif not w.ready and now - w.born > startup_limit:
                    fail(w, "crash", f"not ready after {startup_limit:.0f} s")
                elif w.ready and outstanding(w):
                    busy = outstanding(w)
                    limit = timeout * (2 if any(i in timed_out for i in busy) else 1)
                    if now - w.since > limit:
                        fail(w, "timeout", f"no progress for {limit:.0f} s")
            for w in pool:
                feed(w)
    finally:
        bar.close()
        for w in pool:
            if w.proc.is_alive():
                sample(w)
            w.stop(kill=len(finished) < len(todo))


def _death(w: _Worker, memory_limit_mb: float) -> tuple[str, str]:
    """(event, detail) for a worker that died on its own: crash | memory | killed."""
    code = w.proc.exitcode
    if code == EXIT_MEMORY:
        return "memory", "MemoryError in the worker"
    if code is not None and code < 0:
        sig = signal.Signals(-code)
        if sig in _CRASH_SIGNALS:
            if memory_limit_mb and w.data_mb >= 0.9 * (memory_limit_mb + DATA_HEADROOM_MB):
                return "memory", (f"worker died ({sig.name}) at its memory limit "
                                  f"({w.data_mb:.0f} MB data segment)")
            return "crash", f"worker process died ({sig.name})"
        return "killed", f"worker process killed by {sig.name}"
    return "crash", f"worker process exited with status {code}"
