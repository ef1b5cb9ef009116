"""Distributed build engine: the per-mesh pipeline of ``ucad_cl.build`` as Ray tasks.

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

Failures (no retries: ``max_retries=0``, so one bad file costs one task and the build goes on)
* ``IngestError`` -> rejected with the error's reason, exactly as the local engine does; any other
  exception while loading -> ``unreadable``; after loading -> ``pipeline_error``.
* The worker process dies (a native loader segfaults): Ray raises ``WorkerCrashedError`` (or a
  ``RayTaskError``) -> rejected ``loader_crashed``; other Ray-level losses (node died, object
  lost, out of memory) -> rejected ``worker_lost``.
* ``timeout`` (seconds, optional): a task running longer is cancelled (its worker killed) and
  rejected ``timeout``. Ray does not tell the driver when a task starts; its clock starts when
  fewer than ``cluster CPUs`` earlier-submitted tasks remain unfinished (tasks of one shape are
  scheduled first in, first out), so it can overestimate a task's run time only by scheduler
  latency.
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

INSTALL_HINT = ("the 'ray' engine needs Ray: install it with\n"
                "    pip install -e '.[ray]'      (or: pip install 'ray>=2.9')")

WORKER_ENV = {"POCL_MAX_PTHREAD_COUNT": "1", "POCL_CPU_MAX_CU_NUM": "1", "OMP_NUM_THREADS": "1"}
MARKER_PREFIX = ".ray-shared-"            # staging marker: "<prefix><token>" (see module doc)


def run_ray(todo: list, options, commit: Callable, *, address: str | None = None,
            progress: bool = True, staging: str | os.PathLike, log: Callable = print,
            timeout: float | None = None, num_cpus: int | None = None,
            max_in_flight: int | None = None) -> None:
    """Process ``todo`` (``(MeshRef, sha256)`` pairs) with ``options`` (``BuildOptions``) as Ray
    tasks and ``commit`` every resulting ``CatalogEntry`` in this process, in completion order.

    ``address``: None = start a local cluster (``num_cpus`` CPUs) and stop it at the end, "auto"
    = the running cluster. ``timeout``: seconds one mesh may take (None = no limit).
    ``max_in_flight``: tasks submitted but not committed (default 2 x cluster CPUs).
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
               timeout=timeout, max_in_flight=max_in_flight)
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


def _drive(ray, todo, options, commit, staging: Path, *, progress, log, timeout, max_in_flight):
    from tqdm import tqdm

    from .build import rejected_entry

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
    nxt = 0
    bar = tqdm(total=len(todo), unit="mesh", desc="build (ray)", disable=not progress,
               smoothing=0.05)

    def finish(i, entry):
        commit(entry)
        for data in entry.artifacts.values():       # staged files: committed, not needed now
            if isinstance(data, (str, Path)) and Path(data).is_relative_to(staging):
                Path(data).unlink(missing_ok=True)
        bar.update(1)

    try:
        while nxt < len(todo) or outstanding:
            while nxt < len(todo) and len(outstanding) < limit:
                ref, sha = todo[nxt]
                outstanding[task.remote(ref, sha, options, str(staging), token)] = [nxt, None]
                nxt += 1
            now = time.monotonic()
            for k, slot in enumerate(outstanding.values()):
                if k >= cpus:
                    break
                if slot[1] is None:
                    slot[1] = now                   # (probably) running from now on
            ready, _ = ray.wait(list(outstanding), num_returns=1, timeout=0.5)
            for obj in ready:
                i, _ = outstanding.pop(obj)
                ref, sha = todo[i]
                try:
                    entry = ray.get(obj)
                except Exception as exc:            # Ray-level failure: the task did not return
                    reason = _failure_reason(ray, exc)
                    log(f"rejected {ref.path}: {reason} ({type(exc).__name__})")
                    entry = rejected_entry(ref, sha, reason, f"{ref.path}: Ray task failed: "
                                           f"{type(exc).__name__}: {_first_line(exc)}")
                finish(i, entry)
            if timeout is not None:
                now = time.monotonic()
                for obj, (i, t0) in list(outstanding.items()):
                    if t0 is not None and now - t0 > timeout:
                        ray.cancel(obj, force=True)  # kills the worker process
                        del outstanding[obj]
                        ref, sha = todo[i]
                        log(f"rejected {ref.path}: timeout")
                        finish(i, rejected_entry(ref, sha, "timeout",
                                                 f"{ref.path}: no result within {timeout:g} s "
                                                 "(Ray task cancelled)"))
    finally:
        bar.close()
        for obj in outstanding:                     # interrupted: leave nothing running
            ray.cancel(obj, force=True)
        marker.unlink(missing_ok=True)


def _failure_reason(ray, exc: BaseException) -> str:
    """Reason code for a task that raised at the Ray level (our task function catches its own
    Python exceptions, so these mean the worker process or its node went away)."""
    ex = ray.exceptions
    if isinstance(exc, (ex.WorkerCrashedError, ex.RayTaskError)):
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
        from .build import Pipeline
        pipe = _PIPELINES[key] = Pipeline(options)
    return pipe


def _process_one(ref, sha: str, options, staging: str, token: str):
    """One mesh in a Ray worker -> CatalogEntry (Path artifacts only when the staging folder is
    shared with the driver, else bytes). Same reasons and details as the local engine."""
    from .build import rejected_entry
    from .ingest import IngestError

    pipe = _pipeline(options)
    try:
        mesh, secs = pipe.load(ref)
    except IngestError as exc:
        return rejected_entry(ref, sha, exc.reason, str(exc))
    except Exception as exc:                        # a loader bug must not stop the build
        return rejected_entry(ref, sha, "unreadable", f"{ref.path}: {exc!r}")
    shared = (Path(staging) / f"{MARKER_PREFIX}{token}").is_file()
    out = Path(staging) / f"w{os.getpid()}" if shared else Path(tempfile.mkdtemp(prefix="ucad-ray-"))
    try:
        entry = pipe.process(ref, mesh, secs, out)
        if not shared:
            entry.artifacts = {k: Path(v).read_bytes() if isinstance(v, (str, Path)) else v
                               for k, v in entry.artifacts.items()}
        return entry
    except Exception as exc:
        return rejected_entry(ref, sha, "pipeline_error",
                              f"{ref.path}: {type(exc).__name__}: {exc}")
    finally:
        if not shared:
            shutil.rmtree(out, ignore_errors=True)
