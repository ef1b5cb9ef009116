"""The one place that picks the OpenCL device and builds (and caches) kernel programs.

Device choice, first match wins:
  1. ``get_runtime(device=...)`` / the CLI's ``--device``;
  2. the environment variable ``UCAD_CL_DEVICE``;
  3. the best PoCL CPU device that really compiles a probe kernel, else the first other device
     that does. "Best" (``device_rank``): kernels compiled for a named CPU before a PoCL that
     compiles for the generic x86-64 target; then the newer PoCL, then the newer LLVM. Measured
     on this project's machine (AMD EPYC Zen 3, AVX2, 2 cores), Debian's PoCL 3.1 (LLVM 15)
     ran the exact search kernel 8.2x and Canny 3.3-3.9x faster than the PoCL 3.0-rc2 (LLVM 14) that
     pyopencl's PyPI wheels bundle (``SLOW_POCL_COST``); ``slow_reason`` flags such a device
     and ``ucad-index info`` / the build say so, with the fix (``INSTALL_FAST``).

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
from typing import Any

import numpy as np
from importlib import resources

from . import abi
from .system import IsolatedCallFailed, call_isolated

INSTALL_HINT = (
    "Install the portable CPU runtime from PyPI with\n"
    "    pip install 'pyopencl[pocl]'\n"
    "and, where that PoCL cannot compile for this CPU (newer CPUs: 'unknown target CPU generic'),\n"
    "Debian/Ubuntu's PoCL with\n"
    "    apt-get install pocl-opencl-icd\n"
    "(scripts/setup.sh does both), or a vendor OpenCL driver (an ICD); check with `ucad-index info`."
)


INSTALL_FAST = ("install Debian/Ubuntu's PoCL, built for this CPU family: "
                "`apt-get install pocl-opencl-icd` (scripts/setup.sh does it); it is then "
                "picked by default")
# what a slow PoCL cost when measured (bench/search.py, bench/edges.py; docs/OPENCL.md)
SLOW_POCL_COST = ("measured on an AMD EPYC Zen 3 (AVX2): the exact search kernel 8.2x and Canny "
                  "3.3-3.9x slower than Debian's PoCL 3.1; on an Intel AVX-512 machine 4.2x and "
                  "2.5x")
MIN_FAST_POCL = (3, 1)       # PoCL releases older than this measured slow (see SLOW_POCL_COST)


@dataclass(frozen=True)
class DeviceInfo:
    """What the OpenCL API tells about one device, parsed: ``spec`` "P:D", names, and for PoCL
    its version, LLVM version and the CPU its kernels are compiled for (the device version's
    ``HSTR: <driver>-<triple>-<cpu>``; "generic" or absent = the generic x86-64 target)."""

    spec: str
    platform: str
    device: str
    is_pocl: bool
    pocl_version: tuple[int, ...] | None
    llvm_version: tuple[int, ...] | None
    target_cpu: str | None

    @property
    def generic_target(self) -> bool:
        return self.is_pocl and self.target_cpu in (None, "", "generic", "x86-64")

    def slow_reason(self) -> str | None:
        """Why this device is known to run our kernels slowly, or None."""
        if not self.is_pocl:
            return None
        if self.generic_target:
            return "this PoCL compiles kernels for the generic x86-64 CPU"
        if self.pocl_version is not None and self.pocl_version < MIN_FAST_POCL:
            v = ".".join(map(str, self.pocl_version))
            llvm = ".".join(map(str, self.llvm_version or ()))
            return (f"PoCL {v} (LLVM {llvm or '?'}, the one pyopencl's PyPI wheels bundle) runs "
                    "our kernels several times slower than PoCL >= 3.1")
        return None

    def summary(self) -> str:
        if not self.is_pocl:
            return f"{self.platform} | {self.device}"
        v = ".".join(map(str, self.pocl_version or ())) or "?"
        llvm = ".".join(map(str, self.llvm_version or ())) or "?"
        return (f"{self.platform} | {self.device} | PoCL {v}, LLVM {llvm}, kernels for "
                f"{self.target_cpu or 'generic'!r}")


def device_info(spec: str, platform, device) -> DeviceInfo:
    """Parse the platform / device strings of a pyopencl platform and device."""
    pocl = "portable computing language" in platform.name.lower()
    pv = re.search(r"PoCL (\d+)\.(\d+)", platform.version)
    lv = re.search(r"LLVM (\d+)\.(\d+)(?:\.(\d+))?", platform.version)
    hstr = re.search(r"HSTR:\s*(\S+)", device.version or "")
    cpu = hstr.group(1).rsplit("-", 1)[-1] if hstr else None
    return DeviceInfo(spec, platform.name.strip(), device.name.strip(), pocl,
                      tuple(int(x) for x in pv.groups()) if pv else None,
                      tuple(int(x) for x in lv.groups() if x is not None) if lv else None,
                      cpu if pocl else None)


def device_rank(info: DeviceInfo) -> tuple:
    """Sort key of the default choice, best first (see the module docstring)."""
    return (not info.is_pocl, info.generic_target, tuple(-x for x in info.pocl_version or ()),
            tuple(-x for x in info.llvm_version or ()),
            tuple(int(x) for x in info.spec.split(":")))


class OpenCLUnavailable(RuntimeError):
    """Raised when no usable OpenCL platform/device exists."""


def kernel_source(name: str) -> str:
    """Text of ``ucad_cl/kernels/<name>.cl`` with every ``#include "file"`` inlined (recursively,
    each file once, like ``#pragma once``), so the source string is complete."""
    pkg = resources.files("ucad_cl.kernels")
    seen: set[str] = set()

    def expand(fname: str) -> str:
        seen.add(fname)
        src = (pkg / fname).read_text(encoding="utf-8")
        return re.sub(r'^#include\s+"([^"]+)"\s*$',
                      lambda m: "" if m.group(1) in seen else expand(m.group(1)), src, flags=re.M)

    return expand(f"{name}.cl")


@dataclass
class Runtime:
    """One OpenCL device in use: its context, in-order queue, device, the programs and kernels
    built for it and its scratch buffers. Entry points that touch a device take
    ``runtime: Runtime | None`` (None: ``get_runtime()``). pyopencl types are ``Any`` here so
    that importing this module does not import pyopencl."""

    ctx: Any                                        # pyopencl.Context
    queue: Any                                      # pyopencl.CommandQueue
    device: Any                                     # pyopencl.Device
    info: DeviceInfo | None = None
    why: str = ""                                   # how the device was chosen, one sentence
    compile_seconds: dict = field(default_factory=dict)
    _programs: dict = field(default_factory=dict)
    _kernels: dict = field(default_factory=dict)
    _scratch: dict = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    # held by callers that use kernels and scratch buffers from several threads (``kernel`` and
    # ``scratch`` are not thread-safe): e.g. every FeatureIndex on this runtime
    exclusive: threading.RLock = field(default_factory=threading.RLock)

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
        """Built program for ``ucad_cl/kernels/<name>.cl``, with the kernel ABI's constants
        (``abi.defines()``) and ``options``; cached per process and on disk."""
        import pyopencl as cl

        key = (name, tuple(options))
        with self._lock:
            prg = self._programs.get(key)
            if prg is None:
                t0 = time.perf_counter()
                prg = cl.Program(self.ctx, kernel_source(name)).build(
                    options=["-cl-std=CL1.2", *abi.defines(), *options])
                self.compile_seconds[key] = time.perf_counter() - t0
                self._programs[key] = prg
        return prg


_RUNTIME: Runtime | None = None
_RUNTIME_LOCK = threading.Lock()


def _pick_device(spec: str | None):
    """(device, DeviceInfo, why): the device to use and one sentence on why."""
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except Exception as exc:  # pyopencl raises LogicError/RuntimeError without an ICD
        raise OpenCLUnavailable(f"{INSTALL_HINT}\n(pyopencl said: {exc})") from exc
    devices = [(pi, di, p, d) for pi, p in enumerate(platforms)
               for di, d in enumerate(p.get_devices())]
    infos = {(pi, di): device_info(f"{pi}:{di}", p, d) for pi, di, p, d in devices}
    if not devices:
        raise OpenCLUnavailable(INSTALL_HINT)
    if spec:
        m = re.fullmatch(r"(\d+):(\d+)", spec.strip())
        for pi, di, p, d in devices:
            if (m and (pi, di) == (int(m.group(1)), int(m.group(2)))) or (
                    not m and (spec.lower() in p.name.lower() or spec.lower() in d.name.lower())):
                return d, infos[pi, di], f"selected with --device / UCAD_CL_DEVICE={spec!r}"
        listing = "\n".join(f"  {pi}:{di}  {p.name} | {d.name.strip()}" for pi, di, p, d in devices)
        raise OpenCLUnavailable(f"No OpenCL device matches {spec!r}. Available:\n{listing}")
    # Default: the best-ranked device that really compiles and runs a kernel (device_rank).
    # (The PoCL 3.0-rc2 bundled with pyopencl's PyPI wheels uses LLVM 14, which cannot name newer
    # CPUs such as AMD Zen 5 and fails every build with "unknown target CPU 'generic'"; it is
    # then skipped. See docs/OPENCL.md.)
    ordered = sorted(devices, key=lambda t: device_rank(infos[t[0], t[1]]))
    errors: list[str] = []
    for pi, di, p, d in ordered:
        ok, why = _probe(d)
        if ok:
            others = [infos[t[0], t[1]] for t in ordered if t[:2] != (pi, di)]
            return d, infos[pi, di], _why(infos[pi, di], others, errors)
        errors.append(f"  {pi}:{di}  {p.name} {p.version.strip()} | {d.name.strip()}: {why}")
    raise OpenCLUnavailable("No OpenCL device could compile a kernel:\n" + "\n".join(errors)
                            + "\n" + INSTALL_HINT)


def _why(chosen: DeviceInfo, others: list[DeviceInfo], failed: list[str]) -> str:
    """One sentence: why the default choice is ``chosen`` (the decisive rule per other device)."""
    if not others:
        return "the only OpenCL device"
    parts = []
    for o in others:
        if device_rank(o) < device_rank(chosen):
            continue                                   # better ranked: it failed the probe
        if o.is_pocl != chosen.is_pocl:
            rule = "not PoCL on the CPU"
        elif o.generic_target != chosen.generic_target:
            rule = "compiles for the generic x86-64 CPU"
        elif o.pocl_version != chosen.pocl_version:
            rule = f"older PoCL {'.'.join(map(str, o.pocl_version or ())) or '?'}"
        elif o.llvm_version != chosen.llvm_version:
            rule = f"older LLVM {'.'.join(map(str, o.llvm_version or ())) or '?'}"
        else:
            rule = "listed later"
        parts.append(f"preferred over {o.spec} {o.device} ({rule})")
    if failed:
        parts.append(f"{len(failed)} better-ranked device(s) could not compile a probe kernel")
    return "; ".join(parts) or "the first device that compiles"


def pick_device_info(spec: str | None = None, *,
                     timeout: float = 300.0) -> tuple[DeviceInfo, str]:
    """(DeviceInfo, why) of the device ``get_runtime`` would pick (the build driver uses it to
    report the device its workers will use). The devices are probed in a child process
    (``system.call_isolated``): a process that loads PoCL and its LLVM holds ~150 MB more for
    good, which the driver, which never runs a kernel, should not. ``OpenCLUnavailable`` as
    ``get_runtime`` raises it, and when the probe crashes or runs past ``timeout`` seconds."""
    try:
        return call_isolated(_picked_device_info, spec or os.environ.get("UCAD_CL_DEVICE"),
                             timeout=timeout)
    except IsolatedCallFailed as exc:
        raise OpenCLUnavailable(f"probing the OpenCL devices failed: {exc}\n"
                                f"{INSTALL_HINT}") from None


def _picked_device_info(spec: str | None) -> tuple[DeviceInfo, str]:
    """The child side of ``pick_device_info``."""
    _dev, info, why = _pick_device(spec)
    return info, why


def _probe(dev) -> tuple[bool, str]:
    """Build and run a one-line kernel on ``dev``; (ok, first line of the error)."""
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


def create_runtime(device: str | None = None) -> Runtime:
    """A new runtime (its own context, queue, program and scratch caches) on ``device`` (a spec,
    see the module docstring; None: ``UCAD_CL_DEVICE`` or the best device). Pass it explicitly
    (``runtime=``) to run on a device other than the process default."""
    import pyopencl as cl

    dev, info, why = _pick_device(device or os.environ.get("UCAD_CL_DEVICE"))
    ctx = cl.Context([dev])
    return Runtime(ctx=ctx, queue=cl.CommandQueue(ctx), device=dev, info=info, why=why)


def get_runtime(device: str | None = None) -> Runtime:
    """The process's default runtime, created on first use (``device`` only matters then); used
    by every entry point called without ``runtime=``."""
    global _RUNTIME
    with _RUNTIME_LOCK:
        if _RUNTIME is None:
            _RUNTIME = create_runtime(device)
        return _RUNTIME


def list_devices() -> list[str]:
    """Human-readable list of every OpenCL device: ``"P:D  platform | device | PoCL ..."``."""
    return [f"{i.spec}  {i.summary()}" for i in device_infos()]


def usable_device_specs() -> list[str]:
    """Specs ("P:D") of every device that builds and runs a probe kernel, best first."""
    found = sorted(_devices(), key=lambda t: device_rank(t[0]))
    return [info.spec for info, dev in found if _probe(dev)[0]]


def device_infos() -> list[DeviceInfo]:
    """``DeviceInfo`` of every OpenCL device, in platform / device order (no context made)."""
    return [info for info, _ in _devices()]


def _devices() -> list[tuple[DeviceInfo, Any]]:
    """(DeviceInfo, pyopencl.Device) of every OpenCL device, in platform / device order."""
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except Exception as exc:
        raise OpenCLUnavailable(f"{INSTALL_HINT}\n(pyopencl said: {exc})") from exc
    return [(device_info(f"{pi}:{di}", p, d), d)
            for pi, p in enumerate(platforms) for di, d in enumerate(p.get_devices())]


def slow_device_warning(info: DeviceInfo | None) -> str | None:
    """The warning to print when ``info`` is a device known to be slow, else None."""
    reason = info.slow_reason() if info is not None else None
    if info is None or reason is None:
        return None
    return (f"warning: OpenCL device {info.spec} ({info.device}): {reason}; {SLOW_POCL_COST}. "
            f"Fix: {INSTALL_FAST}.")
