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
    "Install the portable CPU runtime from PyPI with\n"
    "    pip install 'pyopencl[pocl]'\n"
    "and, where that PoCL cannot compile for this CPU (newer CPUs: 'unknown target CPU generic'),\n"
    "Debian/Ubuntu's PoCL with\n"
    "    apt-get install pocl-opencl-icd\n"
    "(scripts/setup.sh does both), or a vendor OpenCL driver (an ICD); check with `ucad-index info`."
)


class OpenCLUnavailable(RuntimeError):
    """Raised when no usable OpenCL platform/device exists."""


def kernel_source(name: str) -> str:
    """Text of ``ucad_cl/kernels/<name>.cl`` with ``#include "common.h"`` inlined."""
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
    _kernels: dict = field(default_factory=dict)
    _scratch: dict = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def is_pocl(self) -> bool:
        return "portable computing language" in self.device.platform.name.lower()

    def describe(self) -> str:
        d = self.device
        return (f"{d.platform.name} {d.platform.version} | {d.name.strip()} | "
                f"{d.max_compute_units} compute units | {d.global_mem_size // 2**20} MiB")

    def kernel(self, program: str, name: str, options: tuple[str, ...] = ()):
        """A cached ``cl.Kernel`` (one per program, options and kernel name; not thread-safe)."""
        import pyopencl as cl

        key = (program, tuple(options), name)
        k = self._kernels.get(key)
        if k is None:
            k = self._kernels[key] = cl.Kernel(self.program(program, options), name)
        return k

    def scratch(self, name: str, nbytes: int):
        """A device buffer of at least ``nbytes`` reused across calls under ``name`` (it grows,
        never shrinks). Saves allocating and first-touching large buffers on every call; the
        contents are undefined. Not thread-safe, like ``kernel``."""
        import pyopencl as cl

        nbytes = max(int(nbytes), 1)
        buf = self._scratch.get(name)
        if buf is None or buf.size < nbytes:
            buf = self._scratch[name] = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes)
        return buf

    def release_scratch(self) -> None:
        """Drop every scratch buffer (e.g. after a very large render)."""
        self._scratch.clear()

    def program(self, name: str, options: tuple[str, ...] = ()):
        """Built program for ``ucad_cl/kernels/<name>.cl``; cached per process and on disk."""
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
    # Default: the first PoCL CPU device that really compiles and runs a kernel, then any other.
    # (The PoCL 3.0-rc2 bundled with pyopencl's PyPI wheels uses LLVM 14, which cannot name newer
    # CPUs such as AMD Zen 5 and fails every build with "unknown target CPU 'generic'"; Debian's
    # pocl-opencl-icd is then used. See README, "OpenCL runtime".)
    ordered = sorted(devices, key=lambda t: "portable computing language" not in t[2].name.lower())
    errors = []
    for pi, di, p, d in ordered:
        ok, why = _probe(d)
        if ok:
            return d
        errors.append(f"  {pi}:{di}  {p.name} {p.version.strip()} | {d.name.strip()}: {why}")
    raise OpenCLUnavailable("No OpenCL device could compile a kernel:\n" + "\n".join(errors)
                            + "\n" + INSTALL_HINT)


def _probe(dev) -> tuple[bool, str]:
    """Build and run a one-line kernel on ``dev``; (ok, first line of the error)."""
    import numpy as np
    import pyopencl as cl

    try:
        ctx = cl.Context([dev])
        q = cl.CommandQueue(ctx)
        prg = cl.Program(ctx, "kernel void probe(global int *a) { a[get_global_id(0)] = 7; }").build()
        buf = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, 4)
        prg.probe(q, (1,), None, buf)
        out = np.zeros(1, np.int32)
        cl.enqueue_copy(q, out, buf)
        q.finish()
        return bool(out[0] == 7), "probe kernel gave a wrong result"
    except Exception as exc:  # build failure, missing compiler, ...
        lines = [ln for ln in str(exc).splitlines() if "error" in ln.lower()]
        return False, (lines[0] if lines else str(exc).splitlines()[0]).strip()


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
