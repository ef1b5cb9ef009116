"""Loaders that stand in for a native mesh reader that crashes or hangs on a broken file, or for a
worker that is paused from outside, for the build's loader seam (``build(..., loader=...)``,
``pipeline.Pipeline(options, loader)``). ``faulty_loader(crash=NAMES, hang=NAMES,
pause_once=NAMES, marks=DIR)`` is picklable, so it reaches spawned workers."""
from __future__ import annotations

import ctypes
import functools
import os
import signal
import time
from pathlib import Path

from ucad_cl.ingest import load_mesh


def _load(path, *, crash=(), hang=(), pause_once=(), marks=None, **kwargs):
    name = str(path)
    if any(n in name for n in crash):
        ctypes.string_at(0)                  # a real fault: SIGSEGV in the worker
    if any(n in name for n in hang):
        time.sleep(3600)
    if any(n in name for n in pause_once) and _first_time(Path(marks) / Path(name).name):
        os.kill(os.getpid(), signal.SIGSTOP)  # the worker stops itself, mid-mesh, as if paused
    return load_mesh(path, **kwargs)


def _first_time(mark: Path) -> bool:
    """True for the first caller across processes (the mark file is created exclusively)."""
    try:
        os.close(os.open(mark, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        return True
    except FileExistsError:
        return False


def faulty_loader(*, crash=(), hang=(), pause_once=(), marks=None):
    """``load_mesh``, except that it segfaults on paths containing a name in ``crash``, hangs on
    those containing a name in ``hang``, and on the first attempt at a path containing a name in
    ``pause_once`` stops its own process with SIGSTOP (``marks``: a folder where the attempts
    are recorded, shared by every worker)."""
    return functools.partial(_load, crash=tuple(crash), hang=tuple(hang),
                             pause_once=tuple(pause_once), marks=marks)
