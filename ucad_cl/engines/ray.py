"""The Ray engine: ``run_ray`` runs the per-mesh pipeline (``ucad_cl.pipeline``) as Ray tasks.

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
  driver (device choice) are forwarded to the workers the same way.
* Each worker process builds one ``ucad_cl.pipeline.Pipeline`` per options hash and reuses it for
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
import shutil
import tempfile
import time
import uuid
from collections import OrderedDict
from pathlib import Path
from typing import Callable

from ..ingest import unreadable_identity
from ..jobs import BuildStopped, KnownContent, Skipped, environment_code, rejected_entry
from ..system import printable

INSTALL_HINT = ("the 'ray' engine needs Ray: install it with\n"
                "    pip install -e '.[ray]'      (or: pip install 'ray>=2.9')")


WORKER_ENV = {"POCL_MAX_PTHREAD_COUNT": "1", "POCL_CPU_MAX_CU_NUM": "1", "OMP_NUM_THREADS": "1"}


MARKER_PREFIX = ".ray-shared-"            # staging marker: "<prefix><token>" (see module doc)


def run_ray(todo: list, options, commit: Callable, *, address: str | None = None,
            progress: bool = True, staging: str | os.PathLike, log: Callable = print,
            timeout: float | None = None, num_cpus: int | None = None,
            max_in_flight: int | None = None, on_skip: Callable | None = None,
            known: tuple = (None, None, ()), summary=None, loader: Callable | None = None) -> None:
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
               summary=summary, loader=loader)
    finally:
        if started:
            ray.shutdown()


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
           on_skip, known, summary, loader):
    from tqdm import tqdm

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
                outstanding[task.remote(ref, force, options, str(staging), token, known,
                                        loader)] = [
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


# (options hash, loader) -> Pipeline: a Ray worker process runs many tasks; its pipeline (OpenCL
# context, kernels, segmenter model) is built once. Per worker process, by design.
_PIPELINES: dict = {}


def _pipeline(options, loader=None):
    key = (options.hash(), None if loader is None else repr(loader))
    pipe = _PIPELINES.get(key)
    if pipe is None:
        # the stages load in the worker only: the driver imports this module and stays small
        from ..pipeline import Pipeline  # noqa: PLC0415
        pipe = _PIPELINES[key] = Pipeline(options, loader)
    return pipe


def _process_one(ref, force: bool, options, staging: str, token: str,
                 known: tuple = (None, None, ()), loader: Callable | None = None):
    """One mesh in a Ray worker -> CatalogEntry (Path artifacts only when the staging folder is
    shared with the driver, else bytes), ``Skipped`` (content already catalogued; checked only
    when the catalogue is shared too), or ("env", code, detail) for an environment fault. Same
    reasons and details as the local engine."""
    pipe = _pipeline(options, loader)
    shared = (Path(staging) / f"{MARKER_PREFIX}{token}").is_file()
    sha, entry = pipe.identify(ref)
    if entry is not None:
        return entry
    if shared and not force and KnownContent(*known)(sha, ref.path):
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
