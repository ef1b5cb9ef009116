"""Loaders that stand in for a native mesh reader that crashes or hangs on a broken file, for
the build's loader seam (``build(..., loader=...)``, ``pipeline.Pipeline(options, loader)``).
``faulty_loader(crash=NAMES, hang=NAMES)`` is picklable, so it reaches spawned workers."""
from __future__ import annotations

import ctypes
import functools
import time

from ucad_cl.ingest import load_mesh


def _load(path, *, crash=(), hang=(), **kwargs):
    name = str(path)
    if any(n in name for n in crash):
        ctypes.string_at(0)                  # a real fault: SIGSEGV in the worker
    if any(n in name for n in hang):
        time.sleep(3600)
    return load_mesh(path, **kwargs)


def faulty_loader(*, crash=(), hang=()):
    """``load_mesh``, except that it segfaults on paths containing a name in ``crash`` and hangs
    on those containing a name in ``hang``."""
    return functools.partial(_load, crash=tuple(crash), hang=tuple(hang))
