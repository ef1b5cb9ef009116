"""The local engine: ``run_local`` runs the per-mesh pipeline (``ucad_cl.pipeline``) in worker
processes on this machine; the policies (attribution, retries, environment faults) are written
once in ``ucad_cl.build``'s docstring.

* ``workers`` spawned processes (``_worker_main``), each with its own OpenCL context and
  ``cores // workers`` PoCL threads; a loader thread prefetches the next mesh while the current
  one is on the device, so a worker holds at most two meshes. Each worker answers through its own
  pipe (a worker that dies mid-message cannot block the others, as it can while holding the
  lock of a shared queue) and publishes the task it is loading / processing in shared memory
  before each step, so a crash still says what it was doing.
* The driver loop (every 0.1 s): handle messages, sample each worker's memory from /proc (tree
  peak, worker peaks, the memory limit), detect dead, unready and stalled workers, feed idle
  ones. A failed worker is killed and replaced; what happens to its meshes is ``build``'s policy.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import queue
import resource
import signal
import threading
import time
from multiprocessing.connection import wait
from pathlib import Path
from typing import Callable

from ..ingest import describe_exception, unreadable_identity
from ..jobs import (BuildOptions, BuildStopped, KnownContent, Skipped, environment_code,
                    rejected_entry)
from ..system import printable, process_memory_mb

EXIT_MEMORY = 86                 # a worker that hit MemoryError exits with this status
DATA_HEADROOM_MB = 1024          # RLIMIT_DATA = memory limit + this (see module doc)
_CRASH_SIGNALS = {signal.SIGSEGV, signal.SIGBUS, signal.SIGILL, signal.SIGFPE, signal.SIGABRT,
                  signal.SIGSYS, signal.SIGTRAP}
_POLL_S = 0.1                    # driver loop: queue wait and memory sampling period
_MAX_STARTS_FAILED = 3
_MAX_KILLS = 3


def _worker_main(wid: int, task_q, conn, state, options_dict: dict, threads: int,
                 staging: str, known: tuple, memory_limit_mb: float,
                 mesh_loader: Callable | None) -> None:
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
    # the stages load in the worker only: the driver imports this module and stays small
    from ..pipeline import Pipeline  # noqa: PLC0415
    pipe = Pipeline(opts, mesh_loader)
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
        try:
            sha, entry = pipe.identify(ref)
            result_q.put(("identity", wid, i, sha))
            if entry is None and not force and is_known(sha, ref.path):
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


def run_local(todo, options, commit, skip, *, workers, timeout,  # noqa: C901  the driver loop
              recycle_after, progress, staging, log, known, memory_limit_mb, summary, runlog,
              loader=None):
    """Process ``todo`` in ``workers`` local processes (see the module docstring); raises
    ``BuildStopped`` on an environment fault. ``known`` = (catalogue, options hash, retried codes)
    for the workers' read-only "already catalogued?" question; ``summary`` gets the memory
    figures and the retry count; ``runlog`` a line per worker failure; ``loader`` (picklable)
    replaces ``ingest.load_mesh`` in the workers."""
    from tqdm import tqdm

    if not todo:
        return
    ctx = mp.get_context("spawn")
    workers = max(1, min(workers, len(todo)))
    threads = max(1, (os.cpu_count() or 1) // workers)
    staging.mkdir(parents=True, exist_ok=True)
    args = (options.to_dict(), threads, str(staging), known, memory_limit_mb, loader)
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
