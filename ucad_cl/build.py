"""``ucad-index build``: a library of meshes -> the part-labelled catalogue.

``build(library, catalog, options)`` discovers meshes, skips those already catalogued with the
same content key and options hash, runs the per-mesh pipeline (ingest -> filter -> render ->
filter by views -> edges -> segment -> classify -> features) in worker processes, and commits
each mesh atomically from the driver, the catalogue's single writer.

Untrusted libraries (decisions; reason codes in ``ucad_cl/reasons.py``)
* The driver loads neither OpenCL nor a model: the segmenter check (a bad ``--segmenter`` fails
  before any work) and the CLI's device report run in child processes
  (``system.call_isolated``), which keeps the driver at ~45 MB instead of ~260 MB (PoCL with its
  LLVM and an onnxruntime session stay in a process's memory for good; ``tests/test_hostile.py``).
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
  outside) are attributed before anything is recorded; meshes it had not started yet simply go
  back in the queue. Memory: a worker that held one mesh records ``too_large``; with two, each
  is retried alone ("solo"). Crash: the meshes it was working on are retried alone and without
  the RLIMIT_DATA soft limit (a failed allocation can kill native code with SIGSEGV/SIGABRT,
  which must not be mistaken for a crash); a second crash records ``loader_crashed``. Timeout
  (no progress for ``timeout`` s): retried once alone with twice the time, then recorded
  (``timeout``): a file that hangs the loader twice would otherwise stop every build forever,
  while a pause of the machine or a stopped worker costs one retry. A worker killed from
  outside (SIGKILL, SIGTERM: the OOM killer, a user) is an environment fault: its meshes are
  retried, and a mesh held by three killed workers stops the build (``worker_killed``),
  recording nothing. Failures before a worker started any mesh (it cannot start, or is over
  its memory limit at idle) are nobody's verdict; three in a row stop the build
  (``worker_start_failed``).
* Environment faults (``disk_full``, ``io_error`` on the catalogue or staging side,
  ``worker_killed``) raise ``BuildStopped``: workers are stopped, nothing is recorded for the
  meshes in flight, and the message says what to free or fix; the next run continues.
* ``retry_failed``: reason codes whose recorded rejections are re-processed even though the file
  and options are unchanged (default for the CLI flag without codes: ``reasons.default_retry()``).

Engines (``ucad_cl.engines``): ``local`` (default) runs ``workers`` processes, each with its own
OpenCL context and ``cores // workers`` PoCL threads, prefetching the next mesh while the current
one is on the device, replaced after ``recycle_after`` meshes so memory stays flat; ``ray`` runs
the same per-mesh functions as Ray tasks on a cluster.

Resumability: a mesh is either fully committed (rows + artifacts) or absent, so a build killed at
any moment (even SIGKILL) and run again continues where it stopped, with nothing duplicated.
A changed file (new content key) is re-processed and replaces the old entry; a change of any
option that affects results changes the options hash, and every mesh with another options hash
is re-processed (its entry replaced in one transaction).

Memory figures: ``BuildSummary.peak_rss_mb`` is the whole process tree (driver + workers,
resident memory summed, sampled every 0.1 s while workers run); ``peak_driver_mb`` the driver's
own peak and ``peak_worker_mb`` the largest worker peak (``VmHWM``; ``ru_maxrss`` of a spawned
process starts at its parent's size).
"""
from __future__ import annotations

import json
import os
import resource
import shutil
import sqlite3
import stat as stat_
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

from ucad_catalog.store import Catalog

from . import reasons
from .engines import run_local, run_ray
from .curation import LabelOverrides, mesh_options_hash
from .ingest import SUPPORTED_SUFFIXES
from .jobs import CODE_VERSION, BuildOptions, BuildStopped, MeshRef, environment_code
from .segment import check_segmenter_spec
from .system import default_memory_limit_mb, printable, process_memory_mb, tree_rss_mb

__all__ = ["build", "discover", "read_uid_list", "library_root", "relative_path", "BuildOptions",
           "BuildStopped", "BuildSummary", "CODE_VERSION", "MeshRef"]


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
    examples: dict = field(default_factory=dict)      # reason -> first few rejected paths
    log_path: str = ""                                # this run's log (every commit, reasons)
    library_root: str = ""

    @property
    def processed(self) -> int:
        return self.accepted + self.rejected

    @property
    def meshes_per_s(self) -> float:
        return self.processed / self.seconds if self.seconds > 0 else 0.0


# ----------------------------------------------------------------------------- discovery

def discover(library: str | os.PathLike, *, uids: Iterable[str] | None = None,
             log=None) -> list[MeshRef]:
    """Mesh files of a library, sorted by path.

    ``library`` is a folder tree (every entry with a supported suffix that is not a directory:
    FIFOs, devices, dangling symlinks and symlink loops included, so each is recorded with its
    reason; hidden names are skipped; symlinked folders are not followed; an Objaverse layout
    ``glbs/<shard>/<uid>.glb`` is such a tree), a single mesh file, or a manifest file (.txt:
    one path per line; .json: a list of paths or ``{"paths": [...]}``), paths relative to the
    manifest's folder. ``uids`` keeps only files whose stem is in it (e.g. Objaverse uids of
    vehicle categories). Only ``stat`` is used on mesh files: nothing is opened. ValueError
    naming the file for a manifest that is not a regular text / JSON file; ``log`` gets a line
    for each folder that cannot be listed.
    """
    root = Path(library)
    if not root.exists():
        raise FileNotFoundError(f"library {root} does not exist")
    if root.is_dir():
        paths = _tree_paths(root, log)
    elif root.suffix.lower() in SUPPORTED_SUFFIXES:
        paths = [root]                                 # one mesh: a library of one
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


def _tree_paths(root: Path, log=None) -> list[Path]:
    """Every non-directory entry with a supported suffix below ``root``, hidden names skipped,
    symlinked folders not followed; iterative, so any depth the file system allows is fine."""
    paths, stack = [], [root]
    while stack:
        folder = stack.pop()
        try:
            with os.scandir(folder) as it:
                entries = list(it)
        except OSError as e:
            if log is not None:
                log(f"warning: cannot list {printable(str(folder))}: {e.strerror}")
            continue
        for e in entries:
            if e.name.startswith("."):
                continue
            try:
                is_dir = e.is_dir(follow_symlinks=False)
            except OSError:
                is_dir = False
            if is_dir:
                stack.append(Path(e.path))
            elif Path(e.name).suffix.lower() in SUPPORTED_SUFFIXES:
                paths.append(Path(e.path))
    return paths


MAX_MANIFEST_BYTES = 256 << 20
INDEX_TIMEOUT = 1800.0      # seconds for the search index's process (1,003 meshes: 2 s)


def _manifest_paths(manifest: Path) -> list[Path]:
    """Paths listed by a .txt / .json manifest (ValueError naming the manifest and the problem).
    The manifest must be a regular file of at most MAX_MANIFEST_BYTES (a library given as
    /dev/zero or a FIFO is refused, not read)."""
    shown = printable(str(manifest))
    st = manifest.stat()
    if not stat_.S_ISREG(st.st_mode):
        raise ValueError(f"{shown}: not a mesh folder, a mesh file "
                         f"({', '.join(SUPPORTED_SUFFIXES)}) or a manifest (.txt one path "
                         "per line, .json list of paths): not a regular file")
    if st.st_size > MAX_MANIFEST_BYTES:
        raise ValueError(f"manifest {shown} has {st.st_size} bytes, more than "
                         f"{MAX_MANIFEST_BYTES}")
    try:
        text = manifest.read_text(encoding="utf-8-sig")      # an editor's BOM dropped
    except UnicodeDecodeError as e:
        raise ValueError(f"{shown}: not a mesh folder, a mesh file "
                         f"({', '.join(SUPPORTED_SUFFIXES)}) or a manifest (.txt one path "
                         f"per line, .json list of paths): not UTF-8 text ({e.reason} at "
                         f"byte {e.start})") from None
    if manifest.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as e:
            raise ValueError(f"{shown}: not a mesh folder, a mesh file "
                             f"({', '.join(SUPPORTED_SUFFIXES)}) or a manifest (.txt one path "
                             f"per line, .json list of paths): {e}") from None
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


def library_root(library: str | os.PathLike) -> str:
    """The absolute folder a library's paths are recorded relative to: the folder itself, or
    the folder holding the manifest / the single mesh file."""
    p = os.path.abspath(library)
    return p if os.path.isdir(p) else os.path.dirname(p)


def relative_path(path: str | os.PathLike, root: str) -> str:
    """``path`` relative to ``root`` with '/' separators; absolute when it lies outside."""
    p = os.path.abspath(path)
    if p == root or not p.startswith(root.rstrip(os.sep) + os.sep):
        return Path(p).as_posix()
    return Path(os.path.relpath(p, root)).as_posix()


UID_COLUMNS = ("uid", "uids", "id", "file_identifier", "fileIdentifier")


def read_uid_list(path: str | os.PathLike, categories: Iterable[str] | None = None) -> list[str]:
    """Uids from a text file (one per line), a Parquet table (column ``uid``, or the first of
    ``UID_COLUMNS``; needs pyarrow) or an Objaverse-style annotations JSON (``{uid: {"name",
    "categories": [{"name": ...}], "tags": [{"name": ...}], ...}}``: its keys). ``categories``
    keeps only annotated uids with a category or tag of one of these names (case-insensitive),
    e.g. ``("car", "vehicle", "truck")``. ValueError naming the file when it is none of these."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"uid list {p} does not exist")
    if p.suffix.lower() in (".parquet", ".pq"):
        if categories:
            raise ValueError(f"{p}: --categories needs an annotations JSON, not a Parquet table")
        return _parquet_uids(p)
    try:
        text = p.read_text(encoding="utf-8-sig")             # an editor's BOM dropped
        data = json.loads(text) if p.suffix.lower() == ".json" else None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{p}: not a uid list (text, one uid per line), a Parquet table "
                         f"(.parquet, column 'uid') or an annotations JSON: {exc}") from None
    if p.suffix.lower() != ".json":
        if categories:
            raise ValueError(f"{p}: --categories needs an annotations JSON, not a uid list")
        return [ln.strip() for ln in text.splitlines() if ln.strip()]
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


def _parquet_uids(p: Path) -> list[str]:
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise ValueError(f"{p}: reading a Parquet uid table needs pyarrow (pip install pyarrow); "
                         "or give a text file with one uid per line") from None
    try:
        schema = pq.read_schema(p)
    except Exception as exc:                # pyarrow raises ArrowInvalid and OSError subclasses
        raise ValueError(f"{p}: not a readable Parquet file ({exc})") from None
    column = next((c for c in UID_COLUMNS if c in schema.names), None)
    if column is None:
        raise ValueError(f"{p}: no uid column (looked for {', '.join(UID_COLUMNS)}; the table has "
                         f"{', '.join(schema.names[:12])})")
    values = pq.read_table(p, columns=[column]).column(column).to_pylist()
    # Objaverse file identifiers are URLs ending in <uid>.glb: keep the stem
    return [Path(str(v)).stem if "/" in str(v) else str(v) for v in values if v is not None]

# ----------------------------------------------------------------------------- driver

def build(library: str | os.PathLike, catalog: str | os.PathLike,
          options: BuildOptions | None = None, *, workers: int = 1, engine: str = "local",
          timeout: float = 600.0, recycle_after: int = 200, progress: bool = True,
          uids: Iterable[str] | None = None, limit: int | None = None,
          ray_address: str | None = None, log=print, retry_failed: Iterable[str] | None = None,
          memory_limit_mb: float | None = None, loader: Callable | None = None) -> BuildSummary:
    """Build or update the catalogue at ``catalog`` from ``library``. See the module docstring.
    ``loader`` replaces ``ingest.load_mesh`` in every worker (``pipeline.Pipeline``'s seam).

    Raises ``BuildStopped`` on an environment fault (the summary of what was done is attached),
    ``ucad_catalog.CatalogError`` when the catalogue cannot be opened (another writer holds it,
    not a catalogue), ValueError / FileNotFoundError for bad arguments or a missing library.
    """
    t_start = time.perf_counter()
    options = options or BuildOptions()
    check_segmenter_spec(options.segmenter)   # a bad --segmenter fails here, not in every worker
    if engine not in ("local", "ray"):
        raise ValueError(f"unknown engine {engine!r}: use local or ray")
    retry = tuple(reasons.check(r, reasons.REJECTION) for r in (retry_failed or ()))
    if memory_limit_mb is None:
        memory_limit_mb = default_memory_limit_mb(workers)
    if not memory_limit_mb > 0:
        raise ValueError(f"memory_limit_mb must be > 0, got {memory_limit_mb}")
    refs = discover(library, uids=uids, log=log)
    if limit:
        refs = refs[:limit]
    root = library_root(library)          # paths are recorded relative to it (absolute root)
    summary = BuildSummary(run_id=0, discovered=len(refs), memory_limit_mb=memory_limit_mb,
                           library_root=root)
    staging = Path(catalog) / "staging"
    cat = sink = None
    try:
        try:
            cat = Catalog.open(catalog, create=True)
            summary.run_id = cat.begin_run(options.run_record(), engine)
            labels = LabelOverrides.from_items(options.label_overrides)
            todo = _plan(cat, refs, root, retry, summary, labels)
            log(f"{len(refs)} meshes found, {summary.skipped} unchanged (skipped), "
                f"{len(todo)} to process with the {engine} engine")
            sink = _Sink(cat, summary, Path(catalog) / "logs" / f"run-{summary.run_id:05d}.log",
                         len(todo), root, labels)
            sink.log.write(f"run {summary.run_id} engine={engine} workers={workers} "
                           f"found={len(refs)} skipped={summary.skipped} todo={len(todo)} "
                           f"memory_limit_mb={memory_limit_mb:.0f} retry={list(retry)} "
                           f"options={options.to_dict()}")
            shutil.rmtree(staging, ignore_errors=True)   # a killed run's leftovers (we hold the lock)
            known = (str(catalog), cat.run_options_hash, retry, options.label_overrides)
            if engine == "local":
                run_local(todo, options, sink.commit, sink.skip, workers=workers,
                          timeout=timeout, recycle_after=recycle_after, progress=progress,
                          staging=staging, log=log, known=known,
                          memory_limit_mb=memory_limit_mb, summary=summary, runlog=sink.log,
                          loader=loader)
            else:
                run_ray(todo, options, sink.commit, address=ray_address, progress=progress,
                        staging=staging, log=log, timeout=timeout,
                        num_cpus=None if ray_address else workers, on_skip=sink.skip,
                        known=known, summary=summary, loader=loader)
            shutil.rmtree(staging, ignore_errors=True)
            sink.log.write(_write_search_index(cat))   # (part of the run's wall time; its
            _finish_summary(summary, t_start, resource)  # peak memory is in its own line)
            summary.superseded_mb = cat.superseded_bytes / 2**20
            cat.finish_run(summary.run_id, {
                "skipped": summary.skipped, "failed": summary.failed, "retried": summary.retried,
                "meshes_per_s": summary.meshes_per_s, "stage_seconds": summary.stage_seconds,
                "peak_rss_mb": summary.peak_rss_mb})
            sink.log.write(f"finished: {summary.accepted} accepted, {summary.rejected} rejected "
                           f"{summary.reasons}, {summary.skipped} skipped, {summary.retried} "
                           f"retried, {summary.meshes_per_s:.2f} meshes/s, peak memory "
                           f"{summary.peak_rss_mb:.0f} MB (process tree), driver "
                           f"{summary.peak_driver_mb:.0f} MB, largest worker "
                           f"{summary.peak_worker_mb:.0f} MB")
        except (OSError, sqlite3.Error) as exc:          # the catalogue side failed
            code = environment_code(exc)
            if code is None:
                raise
            raise BuildStopped(code, f"catalogue {printable(str(catalog))}: "
                                     f"{type(exc).__name__}: {exc}") from None
    except BuildStopped as stop:
        shutil.rmtree(staging, ignore_errors=True)
        _finish_summary(summary, t_start, resource)
        left = sink.todo - summary.processed - sink.worker_skips if sink else len(refs)
        message = _stop_message(stop.code, str(stop), catalog, summary, max(left, 0))
        if sink is not None:
            sink.log.write(f"stopped [{stop.code}]: {message}")
        if cat is not None and summary.run_id:
            try:                                    # best effort: the disk may still be full
                cat.finish_run(summary.run_id, {"skipped": summary.skipped,
                                                "stopped": stop.code})
            except (OSError, sqlite3.Error):
                pass
        raise BuildStopped(stop.code, message, summary) from None
    finally:
        if sink is not None:
            sink.log.close()
        if cat is not None:
            cat.close()
    return summary


def _plan(cat, refs: list[MeshRef], root: str, retry: tuple, summary: BuildSummary,
          labels: LabelOverrides) -> list:
    """(MeshRef, force) for every file to hand to a worker; unchanged ones are counted skipped.

    Unchanged = same (size, mtime) as the last commit of the path (relative to the library
    ``root``), content recorded with this run's options hash (with the mesh's label fixes in
    ``labels``: ``curation.mesh_options_hash``), and not a rejection whose reason is being
    retried (``force``)."""
    run_hash = cat.run_options_hash
    todo = []
    for ref in refs:
        rec = cat.file_record(relative_path(ref.path, root), root)
        if not (rec and rec[1] == ref.size and rec[2] == ref.mtime):
            todo.append((ref, False))               # new or changed: a worker decides
            continue
        verdict = cat.mesh_verdict(rec[0])          # unchanged file: no need to re-hash
        if verdict is None or verdict[2] != mesh_options_hash(run_hash,
                                                              labels.for_mesh(ref.path, rec[0])):
            todo.append((ref, False))
        elif verdict[0] == "rejected" and verdict[1] in retry:
            todo.append((ref, True))
        else:
            summary.skipped += 1
    return todo


class _Sink:
    """Where the engines' results go: commits to the catalogue (an environment fault becomes
    ``BuildStopped`` naming the mesh), the summary's counts, and the run log."""

    def __init__(self, cat, summary: BuildSummary, log_path: Path, todo: int, root: str,
                 labels: LabelOverrides):
        self.cat, self.summary, self.todo, self.root = cat, summary, todo, root
        self.labels = labels
        self.log = RunLog(log_path)
        summary.log_path = str(log_path)
        self.worker_skips = 0                      # paths whose content was already catalogued

    def commit(self, entry) -> None:
        s = self.summary
        fixes = self.labels.for_mesh(entry.path, entry.sha256)   # the path as discovered
        if fixes:
            entry.options_hash = mesh_options_hash(self.cat.run_options_hash, fixes)
        entry.library_root, entry.path = self.root, relative_path(entry.path, self.root)
        try:
            self.cat.commit_mesh(entry, move_files=True)
        except (OSError, sqlite3.Error) as exc:
            code = environment_code(exc)
            if code is None:
                raise
            raise BuildStopped(code, f"storing {printable(entry.path)}: "
                                     f"{type(exc).__name__}: {exc}") from None
        n = s.processed + 1
        self.log.write(f"{n}/{self.todo} {entry.state} {printable(entry.path)}"
                       + (f" reason={entry.reason}: {printable(entry.detail)}"
                          if entry.reason else "")
                       + f" s={sum((entry.timings or {}).values()):.2f}"
                       + (f" rss_mb={tree_rss_mb():.0f}" if n % 50 == 0 else ""))
        if entry.state == "accepted":
            s.accepted += 1
        else:
            s.rejected += 1
            s.reasons[entry.reason] = s.reasons.get(entry.reason, 0) + 1
            s.failed += entry.reason == "pipeline_error"
            examples = s.examples.setdefault(entry.reason, [])
            if len(examples) < 3:
                examples.append(printable(entry.path))
        for k, v in (entry.timings or {}).items():
            s.stage_seconds[k] = s.stage_seconds.get(k, 0.0) + v

    def skip(self, ref: MeshRef, sha: str) -> None:
        self.summary.skipped += 1
        self.worker_skips += 1
        self.log.write(f"skipped {printable(ref.path)}: content {sha[:12]} already catalogued")


def _write_search_index(cat: Catalog) -> str:
    """A line for the run log: the catalogue's search index brought up to date
    (``ucad_catalog.searchindex``) in a process of its own, after the workers, so that the
    driver stays small (the index's fit holds ~0.3 GB over 1,000 meshes; its peak is in the
    line, not in the summary's process-tree peak). A failure is logged, not raised: without a
    fresh index retrieval reads every stored row, as before the index existed."""
    cmd = [sys.executable, "-c", "import sys; from ucad_catalog.searchindex import main; "
           "sys.exit(main(sys.argv[1:]))", str(cat.root)] + ([] if cat.durable else
                                                           ["--no-fsync"])
    t = time.perf_counter()
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=INDEX_TIMEOUT)
    except subprocess.TimeoutExpired:
        return f"search index not written: its process ran over {INDEX_TIMEOUT:g} s"
    except OSError as exc:
        return f"search index not written: {exc}"
    last = (run.stdout.strip().splitlines() or [""])[-1]
    if run.returncode:
        why = last or (run.stderr.strip().splitlines() or [f"exit status {run.returncode}"])[-1]
        return why if why.startswith("search index not written") else \
            f"search index not written: {why}"
    return f"{last} in {time.perf_counter() - t:.1f} s"


def _finish_summary(summary: BuildSummary, t_start: float, resource) -> None:
    summary.seconds = time.perf_counter() - t_start
    summary.peak_driver_mb = (process_memory_mb(os.getpid())[1]
                              or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
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
        self.path = path
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

    def __enter__(self) -> "RunLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._f is not None:
            try:
                self._f.close()
            except OSError:
                pass
            self._f = None
