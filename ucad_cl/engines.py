"""Build engines: the per-mesh pipeline of ``ucad_cl.build`` in local worker processes
(``run_local``, the default) or as Ray tasks (``run_ray``). Both take ``todo`` = ``(MeshRef,
force)`` pairs and call ``commit(entry)`` / ``skip(ref, sha)`` in the driver, the catalogue's
single writer; the policies (attribution, retries, environment faults) are written once in
``ucad_cl.build``'s docstring.

Local engine (``run_local``)
* ``workers`` spawned processes (``_worker_main``), each with its own OpenCL context and
  ``cores // workers`` PoCL threads; a loader thread prefetches the next mesh while the current
  one is on the device, so a worker holds at most two meshes. Each worker answers through its own
  pipe (a worker that dies mid-message cannot block the others, as it can while holding the
  lock of a shared queue) and publishes the task it is loading / processing in shared memory
  before each step, so a crash still says what it was doing.
* The driver loop (every 0.1 s): handle messages, sample each worker's memory from /proc (tree
  peak, worker peaks, the memory limit), detect dead, unready and stalled workers, feed idle
  ones. A failed worker is killed and replaced; what happens to its meshes is ``build``'s policy.

Ray engine (``run_ray``)
``run_ray(todo, options, commit, address=...)`` is what ``build(..., engine="ray")`` calls. The
driver (this process) stays the catalogue's single writer: Ray tasks return
``ucad_catalog.entry.CatalogEntry`` objects and the driver calls ``commit(entry)`` for each, in
completion order. Install the optional extra with ``pip install -e .[ray]`` (``ray`` core).

Cluster
* ``address=None`` starts a local Ray cluster (``num_cpus`` CPUs, default all) and shuts it down
  at the end; ``"auto"`` or ``"ray://host:port"`` / ``"host:port"`` joins an existing one. When
  Ray is already initialised in this process (e.g. by a notebook or a test) that session is used
  as it is and left running.
* Every task takes 1 CPU; its worker runs PoCL with one thread (``POCL_MAX_PTHREAD_COUNT`` =
  ``POCL_CPU_MAX_CU_NUM`` = ``OMP_NUM_THREADS`` = 1 through the task's ``runtime_env``), so N CPUs
  run N meshes at once without oversubscription. Environment variables named ``UCAD_*`` of the
  driver (device choice, test fault injection) are forwarded to the workers the same way.
* Each worker process builds one ``ucad_cl.build.Pipeline`` per options hash and reuses it for
  every task it runs (module-level cache), so OpenCL context and kernels are built once a worker.
* At most ``2 x cluster CPUs`` tasks are in flight (``ray.wait`` loop), so driver and object
  store memory stay flat whatever the library size.
* Commit order (completion order) does not change the catalogue: entries are keyed by content
  hash, and every task is a pure function of (file, options). Exception, shared with the local
  engine: two library files with identical bytes share one entry whose path is the last
  committed one.
* Every node must see the library files at the same paths (shared filesystem or an identical
  copy) and have ``ucad-cl`` installed.

Artifacts (decision): the catalogue folder does NOT have to be on a shared filesystem. The driver
writes a random marker file into the staging folder; a task that sees the marker writes its EXR
there and returns its path (no copy through Ray: the single-node case and shared filesystems); a
task that does not (another node, no shared storage) writes to a private temporary folder and
returns the artifact as bytes through the object store. Either way the driver commits the same
bytes, and removes staged files right after committing them.

Failures (Ray's own retries are off, ``max_retries=0``; reason codes in ``ucad_cl/reasons.py``,
the same decisions as the local engine's, see ``ucad_cl.build``)
* The task reads, hashes (the content key) and parses the file itself; ``IngestError`` ->
  rejected with the error's reason; any other exception while loading -> ``unreadable``; after
  loading -> ``pipeline_error``. A path whose content is already catalogued with these options
  is skipped when the task can see the catalogue (the shared-staging case).
* The worker process dies (a native loader segfaults): Ray raises ``WorkerCrashedError`` ->
  rejected ``loader_crashed`` (a task runs alone in its worker, so the culprit is known); a task
  whose ``MemoryError`` escaped -> ``too_large``.
* Other Ray-level losses (node died, object lost, Ray's memory monitor killed the worker) are
  environment faults: the task is resubmitted, and a mesh lost twice stops the build
  (``BuildStopped``, reason ``worker_lost``). No disk space / I/O error while a task writes its
  staged artifacts stops the build the same way (``disk_full`` / ``io_error``).
* ``timeout`` (seconds, optional): a task running longer is cancelled (its worker killed) and
  resubmitted once with twice the time, then rejected ``timeout``. Ray does not tell the driver
  when a task starts; its clock starts when fewer than ``cluster CPUs`` earlier-submitted tasks
  remain unfinished (tasks of one shape are scheduled first in, first out), so it can
  overestimate a task's run time only by scheduler latency.
* No per-worker memory limit is set by us on Ray (Ray's memory monitor manages its workers).
"""
from __future__ import annotations

import os
import queue
import shutil
import signal
import tempfile
import threading
import time
import uuid
from collections import OrderedDict
from pathlib import Path
from typing import Callable

from .build import (BuildOptions, BuildStopped, KnownContent, Pipeline, Skipped,
                    environment_code, printable, process_memory_mb, rejected_entry)

INSTALL_HINT = ("the 'ray' engine needs Ray: install it with\n"
                "    pip install -e '.[ray]'      (or: pip install 'ray>=2.9')")

WORKER_ENV = {"POCL_MAX_PTHREAD_COUNT": "1", "POCL_CPU_MAX_CU_NUM": "1", "OMP_NUM_THREADS": "1"}
MARKER_PREFIX = ".ray-shared-"            # staging marker: "<prefix><token>" (see module doc)


def run_ray(todo: list, options, commit: Callable, *, address: str | None = None,
            progress: bool = True, staging: str | os.PathLike, log: Callable = print,
            timeout: float | None = None, num_cpus: int | None = None,
            max_in_flight: int | None = None, on_skip: Callable | None = None,
            known: tuple = (None, None, ()), summary=None) -> None:
    """Process ``todo`` (``(MeshRef, force)`` pairs: ``force`` = process even if the content is
    catalogued) with ``options`` (``BuildOptions``) as Ray tasks and ``commit`` every resulting
    ``CatalogEntry`` in this process, in completion order; ``on_skip(ref, sha)`` for paths whose
    content is already catalogued (``known`` = (catalogue path, options hash, retried codes)).

    ``address``: None = start a local cluster (``num_cpus`` CPUs) and stop it at the end, "auto"
    = the running cluster. ``timeout``: seconds one mesh may take (None = no limit).
    ``max_in_flight``: tasks submitted but not committed (default 2 x cluster CPUs).
    ``summary`` (a ``BuildSummary``) counts retries. Raises ``ucad_cl.build.BuildStopped`` on an
    environment fault.
    """
    if timeout is not None and not timeout > 0:
        raise ValueError(f"timeout must be > 0 seconds or None, got {timeout!r}")
    if max_in_flight is not None and max_in_flight < 1:
        raise ValueError(f"max_in_flight must be >= 1, got {max_in_flight!r}")
    if num_cpus is not None and num_cpus < 1:
        raise ValueError(f"num_cpus must be >= 1, got {num_cpus!r}")
    try:
        import ray
    except ImportError as exc:
        raise ImportError(INSTALL_HINT) from exc
    if not todo:
        return
    started = _connect(ray, address, num_cpus, log)
    try:
        _drive(ray, todo, options, commit, Path(staging), progress=progress, log=log,
               timeout=timeout, max_in_flight=max_in_flight, on_skip=on_skip, known=known,
               summary=summary)
    finally:
        if started:
            ray.shutdown()


# ----------------------------------------------------------------------------- driver side

def _connect(ray, address: str | None, num_cpus: int | None, log) -> bool:
    """Initialise Ray; True when we started a local cluster (to be shut down by us)."""
    if ray.is_initialized():
        return False
    kw = dict(include_dashboard=False, logging_level="WARNING", configure_logging=True)
    if address is None:
        ray.init(num_cpus=num_cpus, **kw)
        log(f"started a local Ray cluster ({int(ray.cluster_resources().get('CPU', 0))} CPUs)")
        return True
    try:
        ray.init(address=address, **kw)
    except ConnectionError as exc:
        raise ConnectionError(f"could not connect to the Ray cluster at {address!r} (start one "
                              f"with `ray start --head`, or pass no address for a local "
                              f"cluster): {exc}") from exc
    log(f"connected to Ray at {address} ({int(ray.cluster_resources().get('CPU', 0))} CPUs)")
    return False


def _drive(ray, todo, options, commit, staging: Path, *, progress, log, timeout, max_in_flight,
           on_skip, known, summary):
    from tqdm import tqdm

    from .ingest import unreadable_identity

    cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
    limit = max_in_flight or 2 * cpus
    staging.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex
    marker = staging / f"{MARKER_PREFIX}{token}"
    marker.write_text("the Ray driver's staging folder; workers that see this share it\n")
    env = {**{k: v for k, v in os.environ.items() if k.startswith("UCAD_")}, **WORKER_ENV}
    task = ray.remote(_process_one).options(
        num_cpus=1, max_retries=0, retry_exceptions=False, runtime_env={"env_vars": env})
    outstanding: OrderedDict = OrderedDict()        # ObjectRef -> [index, start time or None]
    queue_ = list(range(len(todo)))[::-1]           # stack: pop() gives the next index
    timed_out: set[int] = set()
    lost: dict[int, int] = {}
    bar = tqdm(total=len(todo), unit="mesh", desc="build (ray)", disable=not progress,
               smoothing=0.05)

    def finish(i, entry):
        commit(entry)
        for data in entry.artifacts.values():       # staged files: committed, not needed now
            if isinstance(data, (str, Path)) and Path(data).is_relative_to(staging):
                Path(data).unlink(missing_ok=True)
        bar.update(1)

    def retried(i, why):
        if summary is not None:
            summary.retried += 1
        log(f"retrying {printable(todo[i][0].path)} ({why})")
        queue_.append(i)

    try:
        while queue_ or outstanding:
            while queue_ and len(outstanding) < limit:
                i = queue_.pop()
                ref, force = todo[i]
                outstanding[task.remote(ref, force, options, str(staging), token, known)] = [
                    i, None]
            now = time.monotonic()
            for k, slot in enumerate(outstanding.values()):
                if k >= cpus:
                    break
                if slot[1] is None:
                    slot[1] = now                   # (probably) running from now on
            ready, _ = ray.wait(list(outstanding), num_returns=1, timeout=0.5)
            for obj in ready:
                i, _ = outstanding.pop(obj)
                ref, _force = todo[i]
                try:
                    result = ray.get(obj)
                except Exception as exc:            # Ray-level failure: the task did not return
                    reason = _failure_reason(ray, exc)
                    if reason == "worker_lost":
                        lost[i] = lost.get(i, 0) + 1
                        if lost[i] >= 2:
                            raise BuildStopped("worker_lost", f"Ray lost the task of "
                                               f"{printable(ref.path)} twice: {type(exc).__name__}"
                                               f": {_first_line(exc)}") from None
                        retried(i, f"{type(exc).__name__}")
                        continue
                    log(f"rejected {printable(ref.path)}: {reason} ({type(exc).__name__})")
                    result = rejected_entry(ref, unreadable_identity(ref.path), reason,
                                            f"{ref.path}: Ray task failed: "
                                            f"{type(exc).__name__}: {_first_line(exc)}")
                if isinstance(result, Skipped):
                    if on_skip is not None:
                        on_skip(ref, result.sha256)
                    bar.update(1)
                elif isinstance(result, tuple):     # ("env", code, detail) from the task
                    raise BuildStopped(result[1], f"{printable(ref.path)}: {result[2]}")
                else:
                    finish(i, result)
            if timeout is not None:
                now = time.monotonic()
                for obj, (i, t0) in list(outstanding.items()):
                    if t0 is not None and now - t0 > timeout * (2 if i in timed_out else 1):
                        ray.cancel(obj, force=True)  # kills the worker process
                        del outstanding[obj]
                        ref, _force = todo[i]
                        if i not in timed_out:
                            timed_out.add(i)
                            retried(i, f"no result within {timeout:g} s")
                            continue
                        log(f"rejected {printable(ref.path)}: timeout")
                        finish(i, rejected_entry(ref, unreadable_identity(ref.path), "timeout",
                                                 f"{ref.path}: no result within {timeout:g} s, "
                                                 f"then {2 * timeout:g} s (Ray task cancelled)"))
    finally:
        bar.close()
        for obj in outstanding:                     # interrupted: leave nothing running
            ray.cancel(obj, force=True)
        marker.unlink(missing_ok=True)


def _failure_reason(ray, exc: BaseException) -> str:
    """Reason code for a task that raised at the Ray level (our task function catches its own
    Python exceptions, so these mean the worker process or its node went away)."""
    ex = ray.exceptions
    if isinstance(exc, ex.RayTaskError):
        cause = getattr(exc, "cause", None)
        return "too_large" if isinstance(cause, MemoryError) else "pipeline_error"
    oom = getattr(ex, "OutOfMemoryError", ())
    if isinstance(exc, ex.WorkerCrashedError) and not (oom and isinstance(exc, oom)):
        return "loader_crashed"
    return "worker_lost"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:300] if text else ""


# ----------------------------------------------------------------------------- worker side

_PIPELINES: dict = {}         # options hash -> ucad_cl.build.Pipeline, one set per worker process


def _pipeline(options):
    key = options.hash()
    pipe = _PIPELINES.get(key)
    if pipe is None:
        pipe = _PIPELINES[key] = Pipeline(options)
    return pipe


def _process_one(ref, force: bool, options, staging: str, token: str,
                 known: tuple = (None, None, ())):
    """One mesh in a Ray worker -> CatalogEntry (Path artifacts only when the staging folder is
    shared with the driver, else bytes), ``Skipped`` (content already catalogued; checked only
    when the catalogue is shared too), or ("env", code, detail) for an environment fault. Same
    reasons and details as the local engine."""

    pipe = _pipeline(options)
    shared = (Path(staging) / f"{MARKER_PREFIX}{token}").is_file()
    sha, entry = pipe.identify(ref)
    if entry is not None:
        return entry
    if shared and not force and KnownContent(*known)(sha):
        return Skipped(sha)
    mesh, secs, entry = pipe.load_entry(ref, sha)
    if entry is not None:
        return entry
    out = Path(staging) / f"w{os.getpid()}" if shared else Path(tempfile.mkdtemp(prefix="ucad-ray-"))
    try:
        entry = pipe.process_entry(ref, mesh, secs, out)
        if not shared:
            entry.artifacts = {k: Path(v).read_bytes() if isinstance(v, (str, Path)) else v
                               for k, v in entry.artifacts.items()}
        return entry
    except OSError as exc:
        code = environment_code(exc)
        if code is None:
            raise
        return ("env", code, f"{type(exc).__name__}: {exc}")
    finally:
        if not shared:
            shutil.rmtree(out, ignore_errors=True)


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
    [index being loaded, index being processed], -1 for none. A task flagged ``unlimited`` (a
    retry after a crash, alone in the worker) runs without the RLIMIT_DATA soft limit, so a
    failed allocation that killed a native library is told apart from a real crash; the RSS
    watchdog still applies. Messages go through this worker's
    own pipe (``conn``): a worker that dies mid-message cannot block the others, as it could
    while holding the lock of a queue they share."""
    send_lock = threading.Lock()

    class _Results:
        @staticmethod
        def put(msg):
            with send_lock:
                conn.send(msg)

    result_q = _Results()
    import resource
    _, hard = resource.getrlimit(resource.RLIMIT_DATA)
    limited = (int((memory_limit_mb + DATA_HEADROOM_MB) * 2**20), hard)
    if memory_limit_mb and (hard == resource.RLIM_INFINITY or hard > limited[0]):
        resource.setrlimit(resource.RLIMIT_DATA, limited)
    else:
        limited = None

    def data_limit(on: bool):
        if limited is not None:
            resource.setrlimit(resource.RLIMIT_DATA, limited if on else (hard, hard))
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
            i, ref, force, unlimited = item
            if unlimited:
                data_limit(False)                       # restored once its result is sent
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
        data_limit(True)


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
        self.peak_mb = 0.0

    def send(self, i, ref, force, unlimited=False):
        self.assigned.append(i)
        self.task_q.put((i, ref, force, unlimited))

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


def run_local(todo, options, commit, skip, *, workers, timeout, recycle_after, progress,
               staging, log, known, memory_limit_mb, summary, runlog):
    """Process ``todo`` in ``workers`` local processes (see the module docstring); raises
    ``BuildStopped`` on an environment fault. ``known`` = (catalogue, options hash, retried codes)
    for the workers' read-only "already catalogued?" question; ``summary`` gets the memory
    figures and the retry count; ``runlog`` a line per worker failure."""
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
    crashed: set[int] = set()                      # retried alone without the data limit
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
            w.send(i, *todo[i], unlimited=i in crashed)

    def finish(i, entry):
        nonlocal starts_failed
        finished.add(i)
        starts_failed = 0                           # workers do work: earlier failures were not
        commit(entry)                               # about starting
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
        active = [i for i in held if i in w.started]
        if not w.ready or (not active and event != "killed"):
            # failed before working on any mesh: not a mesh's fault; three in a row (without a
            # mesh finishing in between) stop the build instead of restarting workers forever
            starts_failed += 1
            runlog.write(f"worker {w.wid} failed before any mesh ({event}: {detail}), "
                         f"{starts_failed} in a row")
            if starts_failed >= _MAX_STARTS_FAILED:
                raise BuildStopped("worker_start_failed",
                                   f"workers failed {starts_failed} times in a row before "
                                   f"working on any mesh (last: {event}: {detail})")
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
            elif event == "crash" and i in crashed:
                record(i, "loader_crashed", f"{detail}, again when retried alone without the "
                                            "data-segment limit")
                continue
            elif event == "crash":
                crashed.add(i)                      # a failed allocation under RLIMIT_DATA can
                solo.add(i)                         # kill native code: retry without it, alone
                pending.append(i)
            elif len(active) == 1 or attempts[i] >= _MAX_KILLS:
                record(i, "too_large", f"{detail} (the worker held only this mesh)"
                       if len(active) == 1 else f"{detail} ({attempts[i]} attempts)")
                continue
            else:
                solo.add(i)
                pending.append(i)
            summary.retried += 1
            log(f"retrying {name} ({event}: {detail})")
        pending.sort(key=lambda k: (k not in solo, -k))   # pop(): in order, solo retries last
        restart(w)

    def sample(w):
        rss, hwm, _ = process_memory_mb(w.proc.pid)
        w.peak_mb = max(w.peak_mb, hwm)
        summary.peak_worker_mb = max(summary.peak_worker_mb, w.peak_mb)
        return rss

    def watch():
        """Sample memory (tree peak, worker peaks) and enforce the memory limit."""
        tree = process_memory_mb(me)[0]
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
                        fail(w, *_death(w))
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


def _death(w: _Worker) -> tuple[str, str]:
    """(event, detail) for a worker that died on its own: crash | memory | killed."""
    code = w.proc.exitcode
    if code == EXIT_MEMORY:
        return "memory", "MemoryError in the worker"
    if code is not None and code < 0:
        sig = signal.Signals(-code)
        if sig in _CRASH_SIGNALS:
            return "crash", f"worker process died ({sig.name})"
        return "killed", f"worker process killed by {sig.name}"
    return "crash", f"worker process exited with status {code}"
