"""The one place that picks the OpenCL device and builds (and caches) kernel programs.

Device choice, first match wins:
  1. ``get_runtime(device=...)`` / the CLI's ``--device``;
  2. the environment variable ``UCAD_CL_DEVICE``;
  3. the PoCL CPU device (installed from PyPI with ``pyopencl[pocl]``), else the first device.

A device spec is ``"P:D"`` (platform and device index, e.g. ``"0:0"``) or a case-insensitive
substring of the platform or device name (e.g. ``"pocl"``, ``"nvidia"``).

Programs are loaded from the installed ``ucad_cl.kernels`` package; ``#include "common.h"`` is
inlined textually so the source string is complete. Built programs are cached in-process (key:
kernel file, options) and on disk by pyopencl's binary cache (key: source, options, device,
driver). PoCL additionally compiles a work-group function at the first launch of each kernel
for each local size (its own disk cache, ``~/.cache/pocl``); ``Runtime.warm_up`` measures that.
The per-device thread count is PoCL's ``POCL_CPU_MAX_CU_NUM`` / ``POCL_MAX_PTHREAD_COUNT``; it
must be set before the first OpenCL call in the process.
"""
from __future__ import annotations

import os
import re
import threading
import time
from dataclasses import dataclass, field
from importlib import resources

INSTALL_HINT = (
    "No OpenCL platform was found. Install the portable CPU runtime from PyPI with\n"
    "    pip install 'pyopencl[pocl]'\n"
    "or install a vendor OpenCL driver (an ICD), then check with `ucad-index info`."
)


class OpenCLUnavailable(RuntimeError):
    """Raised when no usable OpenCL platform/device exists."""


def kernel_source(name: str) -> str:
    """Text of ``kernels/<name>.cl`` with ``#include "common.h"`` inlined."""
    pkg = resources.files("ucad_cl.kernels")
    src = (pkg / f"{name}.cl").read_text(encoding="utf-8")

    def inline(m: re.Match) -> str:
        return (pkg / m.group(1)).read_text(encoding="utf-8")

    return re.sub(r'^#include\s+"([^"]+)"\s*$', inline, src, flags=re.M)


@dataclass
class Runtime:
    ctx: object
    queue: object
    device: object
    compile_seconds: dict = field(default_factory=dict)
    _programs: dict = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def is_pocl(self) -> bool:
        return "portable computing language" in self.device.platform.name.lower()

    def describe(self) -> str:
        d = self.device
        return (f"{d.platform.name} {d.platform.version} | {d.name.strip()} | "
                f"{d.max_compute_units} compute units | {d.global_mem_size // 2**20} MiB")

    def program(self, name: str, options: tuple[str, ...] = ()):
        """Built program for ``kernels/<name>.cl``; cached per process and on disk."""
        import pyopencl as cl

        key = (name, tuple(options))
        with self._lock:
            prg = self._programs.get(key)
            if prg is None:
                t0 = time.perf_counter()
                prg = cl.Program(self.ctx, kernel_source(name)).build(
                    options=["-cl-std=CL1.2", *options])
                self.compile_seconds[key] = time.perf_counter() - t0
                self._programs[key] = prg
        return prg


_RUNTIME: Runtime | None = None
_RUNTIME_LOCK = threading.Lock()


def _pick_device(spec: str | None):
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except Exception as exc:  # pyopencl raises LogicError/RuntimeError without an ICD
        raise OpenCLUnavailable(f"{INSTALL_HINT}\n(pyopencl said: {exc})") from exc
    devices = [(pi, di, p, d) for pi, p in enumerate(platforms)
               for di, d in enumerate(p.get_devices())]
    if not devices:
        raise OpenCLUnavailable(INSTALL_HINT)
    if spec:
        m = re.fullmatch(r"(\d+):(\d+)", spec.strip())
        for pi, di, p, d in devices:
            if m and (pi, di) == (int(m.group(1)), int(m.group(2))):
                return d
            if not m and (spec.lower() in p.name.lower() or spec.lower() in d.name.lower()):
                return d
        listing = "\n".join(f"  {pi}:{di}  {p.name} | {d.name.strip()}" for pi, di, p, d in devices)
        raise OpenCLUnavailable(f"No OpenCL device matches {spec!r}. Available:\n{listing}")
    for pi, di, p, d in devices:
        if "portable computing language" in p.name.lower():
            return d
    return devices[0][3]


def get_runtime(device: str | None = None) -> Runtime:
    """The process-wide runtime (created on first use). ``device`` only matters the first time."""
    global _RUNTIME
    with _RUNTIME_LOCK:
        if _RUNTIME is None:
            import pyopencl as cl

            dev = _pick_device(device or os.environ.get("UCAD_CL_DEVICE"))
            ctx = cl.Context([dev])
            queue = cl.CommandQueue(ctx)
            _RUNTIME = Runtime(ctx=ctx, queue=queue, device=dev)
        return _RUNTIME


def list_devices() -> list[str]:
    """Human-readable list of every OpenCL device, ``"P:D  platform | device"``."""
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except Exception as exc:
        raise OpenCLUnavailable(f"{INSTALL_HINT}\n(pyopencl said: {exc})") from exc
    return [f"{pi}:{di}  {p.name} | {d.name.strip()}"
            for pi, p in enumerate(platforms) for di, d in enumerate(p.get_devices())]
