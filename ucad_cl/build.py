"""``ucad-index build``: a library of meshes -> the part-labelled catalogue.

``build(library, catalog, options)`` discovers meshes, skips those already catalogued with the
same content hash and options hash, runs the per-mesh pipeline (ingest -> filter -> render ->
filter by views -> edges -> segment -> classify -> features) in worker processes, and commits
each mesh atomically from the driver, the catalogue's single writer.

Engines
* ``local`` (default): ``workers`` processes, each with its own OpenCL context and
  ``cores // workers`` PoCL threads (no oversubscription). Inside a worker a loader thread
  prefetches (ingests) the next mesh while the current one is on the OpenCL device. A worker that
  dies (a native loader segfaults) or exceeds ``timeout`` seconds on one mesh is killed and
  replaced; that mesh is recorded as rejected (``loader_crashed`` / ``timeout``) and the build
  goes on. Workers are replaced after ``recycle_after`` meshes so memory stays flat.
* ``ray``: the same per-mesh function as Ray tasks on an existing cluster (``ucad_cl.engines``).

Resumability: a mesh is either fully committed (rows + artifacts) or absent, so a build killed at
any moment (even SIGKILL) and run again continues where it stopped, with nothing duplicated.
A changed file (new content hash) is re-processed and replaces the old entry; a change of any
option that affects results changes the options hash, and every mesh with another options hash
is re-processed (its entry replaced in one transaction).
"""
from __future__ import annotations

import gzip
import hashlib
import io
import json
import os
import queue
import shutil
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from .ingest import SUPPORTED_SUFFIXES

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
    orientation: str = "auto"           # 'auto' | 'file' | 'UP,FRONT' (ucad_cl.orient)
    orientation_overrides: tuple = ()   # ((path or sha256, 'UP,FRONT' | 'auto' | 'file'), ...)
    reject_uncertain_orientation: bool = False   # reject instead of flag (uncertain_orientation)

    def __post_init__(self):
        from .orient import parse_mode

        parse_mode(self.orientation)                      # a bad mode fails here
        object.__setattr__(self, "orientation_overrides",
                           tuple((str(k), str(v)) for k, v in self.orientation_overrides))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["elevations"] = list(self.elevations)
        d["orientation_overrides"] = [list(kv) for kv in self.orientation_overrides]
        return d

    def hash(self) -> str:
        blob = json.dumps({"code": CODE_VERSION, **self.to_dict()}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()


@dataclass
class MeshRef:
    """A library file: path, size in bytes, mtime (s)."""

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
    failed: int = 0
    seconds: float = 0.0
    reasons: dict = field(default_factory=dict)
    stage_seconds: dict = field(default_factory=dict)
    peak_rss_mb: float = 0.0

    @property
    def processed(self) -> int:
        return self.accepted + self.rejected

    @property
    def meshes_per_s(self) -> float:
        return self.processed / self.seconds if self.seconds > 0 else 0.0


# ----------------------------------------------------------------------------- discovery

def discover(library: str | os.PathLike, *, uids: Iterable[str] | None = None) -> list[MeshRef]:
    """Mesh files of a library, sorted by path.

    ``library`` is a folder tree (every file with a supported suffix; an Objaverse layout
    ``glbs/<shard>/<uid>.glb`` is such a tree), or a manifest file (.txt: one path per line;
    .json: a list of paths or ``{"paths": [...]}``), paths relative to the manifest's folder.
    ``uids`` keeps only files whose stem is in it (e.g. Objaverse uids of vehicle categories).
    """
    root = Path(library)
    if not root.exists():
        raise FileNotFoundError(f"library {root} does not exist")
    if root.is_dir():
        paths = [p for p in root.rglob("*") if p.suffix.lower() in SUPPORTED_SUFFIXES
                 and p.is_file() and not p.name.startswith(".")]
    else:
        text = root.read_text(encoding="utf-8")
        if root.suffix.lower() == ".json":
            data = json.loads(text)
            items = data.get("paths", []) if isinstance(data, dict) else data
        else:
            items = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
        paths = [(root.parent / p) if not Path(p).is_absolute() else Path(p) for p in items]
    if uids is not None:
        keep = set(uids)
        paths = [p for p in paths if p.stem in keep]
    refs = []
    for p in sorted(set(paths)):
        try:
            st = p.stat()
            refs.append(MeshRef(str(p), st.st_size, st.st_mtime))
        except OSError:
            refs.append(MeshRef(str(p), -1, 0.0))      # recorded as unreadable later
    return refs


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
    """The mesh key: sha256 of the file (plus external buffers / MTL files), as ingest does."""
    from .ingest import IngestError, file_sha256

    try:
        return file_sha256(path)
    except IngestError:           # unreadable references: key on the file bytes alone
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ----------------------------------------------------------------------------- per mesh

class Pipeline:
    """The per-mesh stages with their state (segmenter, feature extractor) built once."""

    def __init__(self, options: BuildOptions):
        from .cameras import make_ring

        from .orient import OrientationOverrides

        self.options = options
        self.overrides = OrientationOverrides(dict(options.orientation_overrides))
        self.ring = make_ring(azimuth_step=options.azimuth_step, elevations=options.elevations,
                              fov_deg=options.fov_deg, size=options.size)
        self.segmenter = make_segmenter(options.segmenter)
        self.extractor = None
        if options.features:
            from .features import HogExtractor
            self.extractor = HogExtractor()

    def load(self, ref: MeshRef):
        """Ingest, then orient (may raise IngestError). Returns (mesh, {stage: seconds})."""
        from .ingest import load_mesh
        from .orient import orient_mesh

        t0 = time.perf_counter()
        _inject_fault(ref.path)
        mesh = load_mesh(ref.path, orientation=None)
        t1 = time.perf_counter()
        mode = self.overrides.mode_for(ref.path, mesh.sha256, self.options.orientation)
        mesh = orient_mesh(mesh, mode)
        return mesh, {"ingest": t1 - t0, "orient": time.perf_counter() - t1}

    def process(self, ref: MeshRef, mesh, load_seconds: float | dict, staging: Path):
        """Everything after ingest; returns a CatalogEntry (accepted or rejected).
        ``load_seconds``: the ingest seconds, or ``{stage: seconds}`` from ``load``."""
        from ucad_catalog.entry import CatalogEntry
        from ucad_catalog.exr import write_viewset_exr

        from .filter import filter_mesh, filter_views
        from .artifacts import Verdict

        o = self.options
        timings = (dict(load_seconds) if isinstance(load_seconds, dict)
                   else {"ingest": load_seconds})
        t = time.perf_counter()

        def lap(name):
            nonlocal t
            now = time.perf_counter()
            timings[name] = timings.get(name, 0.0) + now - t
            t = now

        def rejected(verdict):
            return CatalogEntry.from_results(sha256=mesh.sha256, path=ref.path, size=ref.size,
                                             mtime=ref.mtime, verdict=verdict, mesh=mesh,
                                             timings=timings)

        orient = mesh.orientation
        if o.reject_uncertain_orientation and orient is not None and orient.uncertain:
            return rejected(Verdict(False, "uncertain_orientation",
                                    f"{ref.path}: orientation confidence up "
                                    f"{orient.up_confidence:.2f}, front "
                                    f"{orient.front_confidence:.2f} (flags: "
                                    f"{', '.join(orient.flags) or 'none'})"))
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
            from .shade import shade_views
            images = shade_views(mesh, views, background=(128, 128, 128))
            feats = self.extractor.extract(images, np.isfinite(views.depth)).feats
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
            verdict=Verdict(True), mesh=mesh, table=table, ring=self.ring, artifacts=artifacts,
            timings=timings, view_stats=view_stats)


def _inject_fault(path: str) -> None:
    """Test hook standing in for a native loader that crashes or hangs on a broken file:
    ``UCAD_FAULT_INJECT="crash:NAME,hang:NAME"`` segfaults / hangs while loading a path that
    contains NAME. Unset in normal use."""
    spec = os.environ.get("UCAD_FAULT_INJECT")
    if not spec:
        return
    import signal
    for item in spec.split(","):
        kind, _, needle = item.partition(":")
        if needle and needle in path:
            if kind == "crash":
                os.kill(os.getpid(), signal.SIGSEGV)
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


# ----------------------------------------------------------------------------- local engine

def _worker_main(task_q, result_q, state, options_dict: dict, threads: int, staging: str) -> None:
    """Worker process: prefetching loader thread + OpenCL stages. Messages to the driver:
    ('loading' | 'loaded' | 'processing', i), ('done', i, entry), ('error', i, reason, detail).
    ``state`` (shared memory, written before each step, so it survives a crash of this process):
    [index being loaded, index being processed], -1 for none."""
    os.environ["POCL_MAX_PTHREAD_COUNT"] = str(threads)
    os.environ["POCL_CPU_MAX_CU_NUM"] = str(threads)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    opts = BuildOptions(**{**options_dict, "elevations": tuple(options_dict["elevations"])})
    pipe = Pipeline(opts)
    loaded: queue.Queue = queue.Queue(maxsize=1)
    parent = os.getppid()

    def get(q):
        """Blocking get that ends the worker when the driver is gone (e.g. killed with -9)."""
        while True:
            try:
                return q.get(timeout=1.0)
            except queue.Empty:
                if os.getppid() != parent:
                    os._exit(0)

    def loader():
        from .ingest import IngestError
        while True:
            item = get(task_q)
            if item is None:
                loaded.put(None)
                return
            i, ref = item
            state[0] = i
            result_q.put(("loading", i))
            try:
                mesh, secs = pipe.load(ref)
                out = (i, ref, mesh, secs, None)
            except IngestError as exc:
                out = (i, ref, None, 0.0, (exc.reason, str(exc)))
            except Exception as exc:            # a loader bug must not stop the build
                out = (i, ref, None, 0.0, ("unreadable", f"{ref.path}: {exc!r}"))
            state[0] = -1
            result_q.put(("loaded", i))
            loaded.put(out)

    threading.Thread(target=loader, daemon=True).start()
    stage_dir = Path(staging) / f"w{os.getpid()}"
    while True:
        item = get(loaded)
        if item is None:
            return
        i, ref, mesh, secs, err = item
        state[1] = i
        result_q.put(("processing", i))
        if err is not None:
            msg = ("error", i, err[0], err[1])
        else:
            try:
                msg = ("done", i, pipe.process(ref, mesh, secs, stage_dir))
            except Exception as exc:
                msg = ("error", i, "pipeline_error", f"{ref.path}: {type(exc).__name__}: {exc}")
        state[1] = -1
        result_q.put(msg)


class _Worker:
    def __init__(self, ctx, result_q, options, threads, staging):
        self.task_q = ctx.Queue()
        self.state = ctx.Array("q", [-1, -1], lock=False)
        self.proc = ctx.Process(target=_worker_main, daemon=True,
                                args=(self.task_q, result_q, self.state, options.to_dict(),
                                      threads, staging))
        self.proc.start()
        self.assigned: list[int] = []          # task indices sent, in order
        self.since = time.monotonic()
        self.done = 0

    def send(self, i, ref):
        self.assigned.append(i)
        self.task_q.put((i, ref))



    def stop(self, kill=False):
        if kill:
            self.proc.kill()
        else:
            self.task_q.put(None)
        self.proc.join(timeout=10)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()


def build(library: str | os.PathLike, catalog: str | os.PathLike,
          options: BuildOptions = BuildOptions(), *, workers: int = 1, engine: str = "local",
          timeout: float = 600.0, recycle_after: int = 200, progress: bool = True,
          uids: Iterable[str] | None = None, limit: int | None = None,
          ray_address: str | None = None, log=print) -> BuildSummary:
    """Build or update the catalogue at ``catalog`` from ``library``. See the module docstring."""
    import resource

    from ucad_catalog.store import Catalog

    t_start = time.perf_counter()
    make_segmenter(options.segmenter)     # a bad --segmenter fails here, not in every worker
    refs = discover(library, uids=uids)
    if limit:
        refs = refs[:limit]
    cat = Catalog.open(catalog, create=True)
    try:
        run_id = cat.begin_run({**options.to_dict(), "code": CODE_VERSION}, engine)
        ohash = cat.run_options_hash
        summary = BuildSummary(run_id=run_id, discovered=len(refs))
        todo: list[tuple[MeshRef, str]] = []
        for ref in refs:
            rec = cat.file_record(ref.path)
            if rec and rec[1] == ref.size and rec[2] == ref.mtime:
                sha = rec[0]                               # unchanged file: no need to re-hash
            else:
                try:
                    sha = content_sha256(ref.path)
                except OSError:
                    sha = hashlib.sha256(f"unreadable:{ref.path}".encode()).hexdigest()
            if cat.needs_processing(ref.path, sha, ohash):
                todo.append((ref, sha))
            else:
                summary.skipped += 1
        log(f"{len(refs)} meshes found, {summary.skipped} unchanged (skipped), "
            f"{len(todo)} to process with the {engine} engine")
        runlog = RunLog(Path(catalog) / "logs" / f"run-{run_id:05d}.log")
        runlog.write(f"run {run_id} engine={engine} workers={workers} found={len(refs)} "
                     f"skipped={summary.skipped} todo={len(todo)} options={options.to_dict()}")

        def commit(entry):
            cat.commit_mesh(entry, move_files=True)
            n = summary.processed + 1
            runlog.write(f"{n}/{len(todo)} {entry.state} {entry.path}"
                         + (f" reason={entry.reason}: {entry.detail}" if entry.reason else "")
                         + f" s={sum((entry.timings or {}).values()):.2f}"
                         + (f" rss_mb={_tree_rss_mb():.0f}" if n % 50 == 0 else ""))
            if entry.state == "accepted":
                summary.accepted += 1
            else:
                summary.rejected += 1
                summary.reasons[entry.reason] = summary.reasons.get(entry.reason, 0) + 1
            for k, v in (entry.timings or {}).items():
                summary.stage_seconds[k] = summary.stage_seconds.get(k, 0.0) + v

        staging = Path(catalog) / "staging"
        if engine == "local":
            _run_local(todo, options, commit, workers=workers, timeout=timeout,
                       recycle_after=recycle_after, progress=progress, staging=staging, log=log)
        elif engine == "ray":
            from .engines import run_ray
            run_ray(todo, options, commit, address=ray_address, progress=progress,
                    staging=staging, log=log, timeout=timeout,
                    num_cpus=None if ray_address else workers)
        else:
            raise ValueError(f"unknown engine {engine!r}: use local or ray")
        shutil.rmtree(staging, ignore_errors=True)
        summary.seconds = time.perf_counter() - t_start
        summary.peak_rss_mb = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                                  resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024
        cat.finish_run(run_id, {"skipped": summary.skipped, "failed": summary.failed,
                                "meshes_per_s": summary.meshes_per_s,
                                "stage_seconds": summary.stage_seconds})
        runlog.write(f"finished: {summary.accepted} accepted, {summary.rejected} rejected "
                     f"{summary.reasons}, {summary.meshes_per_s:.2f} meshes/s, "
                     f"peak RSS {summary.peak_rss_mb:.0f} MB")
    finally:
        cat.close()
    return summary


class RunLog:
    """Append-only, line-buffered log of one run (``CATALOG/logs/run-NNNNN.log``): every commit
    with its reason and seconds, process-tree memory every 50 meshes, worker deaths. Flushed per
    line, so a killed run still says how far it got and why."""

    def __init__(self, path: Path):
        path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(path, "a", buffering=1, encoding="utf-8")

    def write(self, line: str) -> None:
        self._f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {line}\n")


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


def _run_local(todo, options, commit, *, workers, timeout, recycle_after, progress, staging, log):
    import multiprocessing as mp

    from tqdm import tqdm

    if not todo:
        return
    ctx = mp.get_context("spawn")
    workers = max(1, min(workers, len(todo)))
    threads = max(1, (os.cpu_count() or 1) // workers)
    result_q = ctx.Queue()
    staging.mkdir(parents=True, exist_ok=True)
    pool = [_Worker(ctx, result_q, options, threads, str(staging)) for _ in range(workers)]
    pending = list(range(len(todo)))[::-1]          # stack: pop() gives the next index
    finished: set[int] = set()
    bar = tqdm(total=len(todo), unit="mesh", desc="build", disable=not progress, smoothing=0.05)

    def outstanding(w):
        return [i for i in w.assigned if i not in finished]

    def feed(w):
        # at most two tasks per worker: one on the device, one being prefetched; a worker takes
        # no more than recycle_after tasks in its life
        while pending and len(outstanding(w)) < 2 and len(w.assigned) < recycle_after:
            i = pending.pop()
            w.send(i, todo[i][0])

    def finish(i, entry):
        finished.add(i)
        commit(entry)
        bar.update(1)

    def replace(w, reason, detail, kill=True):
        """Worker died or hung: reject its current mesh, requeue the rest, start a new one."""
        w.stop(kill=kill)
        loading, processing = w.state[0], w.state[1]
        culprit = loading if loading >= 0 and loading not in finished else processing
        for i in reversed(outstanding(w)):
            if i == culprit:
                ref, sha = todo[i]
                log(f"rejected {ref.path}: {detail}")
                finish(i, rejected_entry(ref, sha, reason, f"{ref.path}: {detail}"))
            else:
                pending.append(i)
        nw = _Worker(ctx, result_q, options, threads, str(staging))
        pool[pool.index(w)] = nw
        feed(nw)

    for w in pool:
        feed(w)
    try:
        while len(finished) < len(todo):
            try:
                msg = result_q.get(timeout=0.5)
            except queue.Empty:
                msg = None
            if msg is not None:
                kind, i = msg[0], msg[1]
                w = next((w for w in pool if i in w.assigned), None)
                if w is None or i in finished:
                    continue
                if kind in ("loading", "loaded", "processing"):
                    w.since = time.monotonic()
                else:
                    ref, sha = todo[i]
                    entry = msg[2] if kind == "done" else rejected_entry(ref, sha, msg[2], msg[3])
                    w.done += 1
                    finish(i, entry)
                    if len(w.assigned) >= recycle_after and not outstanding(w):
                        w.stop()                      # recycle: memory stays flat
                        nw = _Worker(ctx, result_q, options, threads, str(staging))
                        pool[pool.index(w)] = nw
                        w = nw
                    feed(w)
            for w in list(pool):
                busy = outstanding(w)
                if busy and not w.proc.is_alive():
                    code = w.proc.exitcode
                    replace(w, "loader_crashed", f"worker process died (exit code {code}) "
                            "while loading or processing this mesh", kill=False)
                elif busy and time.monotonic() - w.since > timeout:
                    replace(w, "timeout", f"no progress for {timeout:.0f} s on this mesh")
    finally:
        bar.close()
        for w in pool:
            w.stop(kill=len(finished) < len(todo))
