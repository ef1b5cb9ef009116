"""The one place that picks the OpenCL device and builds (and caches) kernel programs.

A device is **usable** only when it passes this project's self-test (``ucad_cl/selftest.py``:
every kernel built and created, a small render, Canny and search checked against NumPy / OpenCV),
run in a child process so that a broken OpenCL compiler cannot abort the caller, and cached on
disk per device, driver and kernel sources (``device_status``; ``$XDG_CACHE_HOME/ucad-cl``).
PyPI's PoCL 3.0 on an AMD Zen 4 is such a device: it builds our programs, cannot create their
kernels, and its LLVM aborts the interpreter at exit.

Device choice, first match wins:
  1. ``get_runtime(device=...)`` / the CLI's ``--device``;
  2. the environment variable ``UCAD_CL_DEVICE``;
  (1 and 2 must name a usable device: an unusable one is refused with the self-test's reason)
  3. the best-ranked usable device (``device_rank``): a GPU first (measured: an NVIDIA H100
     rendered 100k triangles x 72 views at 256 px at 13,900 views/s, where a 2-core PoCL CPU
     does ~770); then a PoCL CPU device, kernels compiled for a named CPU before the generic
     x86-64 target, then the newer PoCL, then the newer LLVM. Measured on this project's machine
     (AMD EPYC Zen 3, AVX2, 2 cores), Debian's PoCL 3.1 (LLVM 15) ran the exact search kernel
     8.2x and Canny 3.3-3.9x faster than the PoCL 3.0-rc2 (LLVM 14) that pyopencl's PyPI wheels
     bundle (``SLOW_POCL_COST``); ``slow_reason`` flags such a device and ``ucad-index info`` /
     the build say so, with the fix (``INSTALL_FAST``). Outputs are the same bytes on every
     usable device (tests/test_render.py, tests/test_edges.py compare them).

A device spec is ``"P:D"`` (platform and device index, e.g. ``"0:0"``) or a case-insensitive
substring of the platform or device name (e.g. ``"pocl"``, ``"nvidia"``).

Programs are loaded from the installed ``ucad_cl.kernels`` package; ``#include "common.h"`` is
inlined textually so the source string is complete. Built programs are cached in-process (key:
kernel file, options) and their binaries on disk (``program_cache_dir``; key: source, options,
device, driver; pyopencl leaves PoCL to its own source cache, ~25 ms a program against ~3-9 ms
from a binary). PoCL additionally compiles a work-group function at the first launch of each kernel
for each local size (its own disk cache, ``~/.cache/pocl``); ``Runtime.warm_up`` measures that.
The per-device thread count is PoCL's ``POCL_CPU_MAX_CU_NUM`` / ``POCL_MAX_PTHREAD_COUNT``; it
must be set before the first OpenCL call in the process.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from importlib import resources

import numpy as np

from . import abi
from .system import IsolatedCallFailed, call_isolated

INSTALL_HINT = ("install Debian/Ubuntu's PoCL (`apt-get install pocl-opencl-icd`; scripts/setup.sh "
                "does it and pyopencl[pocl]) or a vendor OpenCL driver (an ICD); "
                "`ucad-index info` lists every device and why it is or is not usable")
#: built programs' binaries kept on disk at most (``program_cache_dir``)
PROGRAM_CACHE_FILES = 128
#: the self-test, run by name in a child process (``system.call_isolated``)
SELF_TEST = "ucad_cl.selftest:check_device"
SELF_TEST_TIMEOUT_S = 900.0
#: files whose text decides a self-test verdict (with the device and its driver): the cache key
SELF_TEST_SOURCES = ("selftest.py", "runtime.py", "abi.py", "render.py", "edges.py", "search.py")


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
    kind: str = "cpu"                   # "cpu", "gpu", "accelerator" or "other"
    driver: str = ""                    # platform version | device version | driver version

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
            return f"{self.platform} | {self.device} | {self.kind}, {self.driver}"
        v = ".".join(map(str, self.pocl_version or ())) or "?"
        llvm = ".".join(map(str, self.llvm_version or ())) or "?"
        return (f"{self.platform} | {self.device} | PoCL {v}, LLVM {llvm}, kernels for "
                f"{self.target_cpu or 'generic'!r}")


def device_info(spec: str, platform, device) -> DeviceInfo:
    """Parse the platform / device strings of a pyopencl platform and device."""
    import pyopencl as cl

    pocl = "portable computing language" in platform.name.lower()
    t = int(device.type)
    kind = ("gpu" if t & cl.device_type.GPU else "accelerator" if t & cl.device_type.ACCELERATOR
            else "cpu" if t & cl.device_type.CPU else "other")
    driver = " | ".join(x.strip() for x in (platform.version, device.version,
                                            device.driver_version))
    pv = re.search(r"PoCL (\d+)\.(\d+)", platform.version)
    lv = re.search(r"LLVM (\d+)\.(\d+)(?:\.(\d+))?", platform.version)
    hstr = re.search(r"HSTR:\s*(\S+)", device.version or "")
    cpu = hstr.group(1).rsplit("-", 1)[-1] if hstr else None
    return DeviceInfo(spec, platform.name.strip(), device.name.strip(), pocl,
                      tuple(int(x) for x in pv.groups()) if pv else None,
                      tuple(int(x) for x in lv.groups() if x is not None) if lv else None,
                      cpu if pocl else None, kind, driver)


def device_rank(info: DeviceInfo) -> tuple:
    """Sort key of the default choice among usable devices, best first (see the module
    docstring): a GPU, then PoCL on the CPU by target, PoCL and LLVM version; then the spec."""
    return (info.kind != "gpu", not info.is_pocl, info.generic_target, tuple(-x for x in info.pocl_version or ()),
            tuple(-x for x in info.llvm_version or ()),
            tuple(int(x) for x in info.spec.split(":")))


class OpenCLUnavailable(RuntimeError):
    """Raised when no usable OpenCL platform/device exists."""


def aligned_empty(shape, dtype, align: int = 4096) -> np.ndarray:
    """np.empty whose data starts on an ``align``-byte boundary, for host arrays a kernel writes in
    place (a USE_HOST_PTR buffer: PoCL copies one that is not aligned)."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape)) * dtype.itemsize
    raw = np.empty(n + align, np.uint8)
    off = (-raw.ctypes.data) % align
    return raw[off:off + n].view(dtype).reshape(shape)


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
        key = (name, tuple(options))
        with self._lock:
            prg = self._programs.get(key)
            if prg is None:
                t0 = time.perf_counter()
                prg = self.build_source(kernel_source(name), options)
                self.compile_seconds[key] = time.perf_counter() - t0
                self._programs[key] = prg
        return prg

    def build_source(self, source: str, options: tuple[str, ...] = ()):
        """A program built from OpenCL C ``source`` with the options every program of this
        project gets (OpenCL C 1.2, the kernel ABI's constants, float division and sqrt
        correctly rounded where the device offers it: OpenCL otherwise allows 2.5 / 3 ulp, and
        NVIDIA's defaults differ from PoCL's) and ``options``; not cached."""
        import pyopencl as cl

        exact = (["-cl-fp32-correctly-rounded-divide-sqrt"]
                 if self.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT
                 else [])
        return _build_cached(self.ctx, self.device, source,
                             ["-cl-std=CL1.2", *abi.defines(), *exact, *options])


def _build_cached(ctx, device, source: str, options: list[str]):
    """``cl.Program(ctx, source).build(options)``, its binary kept on disk
    (``program_cache_dir()``, key: the device, its platform and driver versions, the source and
    the options) and built from there the next time. Why: PoCL's own cache (which pyopencl
    relies on for PoCL, skipping its binary cache) still costs ~25 ms a program to find a cached
    build from source, a binary ~3-9 ms; a lone ``ucad-index fit`` builds 3-8 programs. A
    binary whose checksum does not match, or that the driver refuses, is built from source
    again; a cache that cannot be written is skipped."""
    import pyopencl as cl

    ident = [device.platform.name, device.platform.version, device.name, device.version,
             device.driver_version]
    key = hashlib.sha256(json.dumps([ident, source, options]).encode()).hexdigest()[:40]
    path = program_cache_dir() / f"{key}.bin"
    try:
        blob = path.read_bytes()
        if len(blob) > 32 and hashlib.sha256(blob[32:]).digest() == blob[:32]:
            with _quiet_build():
                return cl.Program(ctx, [device], [blob[32:]]).build(options=options)
    except (OSError, cl.Error):
        pass                                    # absent, unreadable or refused: from source
    with _quiet_build():
        prg = cl.Program(ctx, source).build(options=options)
    try:
        binary = bytes(prg.get_info(cl.program_info.BINARIES)[0])
    except cl.Error:
        binary = b""
    if binary and _cache_write(path, hashlib.sha256(binary).digest() + binary):
        _prune(path.parent, PROGRAM_CACHE_FILES)
    return prg


@contextlib.contextmanager
def _quiet_build():
    """Where a build succeeds, its compiler log is not the user's concern: pyopencl warns
    (``CompilerWarning``, two lines on stderr) at every build whose log is not empty, and
    Debian's PoCL 3.1 compiling for 'haswell' on a CPU whose AVX-512 is hidden logs ABI notes
    on our 16-wide vector types at every build, from the binary too, so every ``ucad-index``
    call printed them. Silenced unless ``PYOPENCL_COMPILER_OUTPUT`` is set (pyopencl's own
    switch, which then shows the whole log); a failed build still raises with its log. (The
    warnings filter is process-wide: a warning of another thread during a build is silenced
    too, which only ever drops this category.)"""
    import pyopencl as cl

    with warnings.catch_warnings():
        if not os.environ.get("PYOPENCL_COMPILER_OUTPUT"):
            warnings.simplefilter("ignore", cl.CompilerWarning)
        yield


def _cache_write(path: Path, data: bytes) -> bool:
    """Write ``data`` to the cache file ``path`` atomically (a temporary file renamed over it);
    False when it cannot be written (a read-only home: the cache is skipped, not an error)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError:
        return False
    return True


def _prune(folder: Path, keep: int) -> None:
    """Delete all but the ``keep`` most recently written ``*.bin`` files of ``folder``."""
    files = []
    for p in folder.glob("*.bin"):
        try:
            files.append((p.stat().st_mtime_ns, p.name, p))
        except OSError:
            pass
    for _, _, p in sorted(files, reverse=True)[keep:]:
        try:
            p.unlink()
        except OSError:
            pass


_RUNTIME: Runtime | None = None
_RUNTIME_LOCK = threading.Lock()


def _pick_device(spec: str | None):
    """(device, DeviceInfo, why): the device to use and one sentence on why. Only a usable
    device (``device_status``) is returned; OpenCLUnavailable (one line) otherwise."""
    devices = _devices()
    if not devices:
        raise OpenCLUnavailable(f"no OpenCL device found; {INSTALL_HINT}")
    if spec:
        info, dev = _match(spec, devices)
        status = device_status(info)
        if not status.usable:
            raise OpenCLUnavailable(f"OpenCL device {info.spec} ({info.device}) cannot run "
                                    f"ucad-cl's kernels: {status.reason}; choose another with "
                                    f"--device / UCAD_CL_DEVICE, or {INSTALL_HINT}")
        return dev, info, f"selected with --device / UCAD_CL_DEVICE={spec!r}"
    ordered = sorted(devices, key=lambda t: device_rank(t[0]))
    failed: list[DeviceStatus] = []
    for info, dev in ordered:
        status = device_status(info)
        if status.usable:
            others = [i for i, _ in ordered if i.spec != info.spec]
            return dev, info, _why(info, others, failed)
        failed.append(status)
    raise OpenCLUnavailable("no usable OpenCL device ("
                            + "; ".join(f"{f.info.spec} {f.info.device}: {f.reason}"
                                        for f in failed) + f"); {INSTALL_HINT}")


def _match(spec: str, devices: list[tuple[DeviceInfo, Any]]) -> tuple[DeviceInfo, Any]:
    """The device a spec names: "P:D", or a case-insensitive substring of the platform or
    device name (the first match in platform / device order)."""
    m = re.fullmatch(r"(\d+):(\d+)", spec.strip())
    for info, dev in devices:
        if (m and info.spec == f"{int(m.group(1))}:{int(m.group(2))}") or (
                not m and (spec.lower() in info.platform.lower()
                           or spec.lower() in info.device.lower())):
            return info, dev
    listing = "; ".join(f"{i.spec} {i.platform} | {i.device}" for i, _ in devices)
    raise OpenCLUnavailable(f"no OpenCL device matches {spec!r} (available: {listing})")


def _why(chosen: DeviceInfo, others: list[DeviceInfo], failed: list[DeviceStatus]) -> str:
    """One sentence: why the default choice is ``chosen`` (the decisive rule per other device)."""
    if not others:
        return "the only OpenCL device"
    parts = []
    for o in others:
        if device_rank(o) < device_rank(chosen):
            continue                                   # better ranked: it failed the self-test
        if (o.kind == "gpu") != (chosen.kind == "gpu"):
            rule = "not a GPU"
        elif o.is_pocl != chosen.is_pocl:
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
    parts += [f"{f.info.spec} {f.info.device} is unusable ({f.reason})" for f in failed]
    return "; ".join(parts) or "the first usable device"


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


@dataclass(frozen=True)
class DeviceStatus:
    """The self-test's verdict on one device: ``usable``, else ``reason`` (one line);
    ``seconds`` the self-test took when it ran; ``cached`` when read from the disk cache."""

    info: DeviceInfo
    usable: bool
    reason: str = ""
    seconds: float = 0.0
    cached: bool = False


def device_status(info: DeviceInfo, *, checks: tuple[str, ...] | None = None,
                  refresh: bool = False, timeout: float = SELF_TEST_TIMEOUT_S) -> DeviceStatus:
    """Whether ``info``'s device runs this project's kernels correctly: the self-test
    (``ucad_cl/selftest.py``) run in a child process, so that a compiler that crashes or
    aborts (also at exit) harms only the child. The verdict of the default checks is cached on
    disk (``self_test_cache_dir()``), keyed by the device, its driver and the text of
    SELF_TEST_SOURCES and the kernels; ``refresh`` runs it again. ``checks``: other checks
    ("module:function", see ``selftest.check_device``), never cached."""
    path = self_test_cache_dir() / f"{_status_key(info)}.json"
    if checks is None and not refresh:
        try:
            rec = json.loads(path.read_text())
            return DeviceStatus(info, bool(rec["usable"]), str(rec["reason"]),
                                float(rec["seconds"]), cached=True)
        except (OSError, ValueError, KeyError, TypeError):
            pass
    args = (info.spec,) if checks is None else (info.spec, checks)
    try:
        seconds = float(call_isolated(SELF_TEST, *args, timeout=timeout, clean_exit=True))
        status = DeviceStatus(info, True, "", round(seconds, 3))
    except IsolatedCallFailed as exc:
        status = DeviceStatus(info, False, f"the self-test's process {exc.how}")
    except Exception as exc:  # noqa: BLE001 - SelfTestFailed, or the device could not open
        status = DeviceStatus(info, False, (str(exc).strip().splitlines() or [""])[0]
                              or type(exc).__name__)
    if checks is None:                                 # (a read-only home: test again next time)
        _cache_write(path, json.dumps({"device": info.summary(), "usable": status.usable,
                                       "reason": status.reason,
                                       "seconds": status.seconds}).encode())
    return status


def self_test_cache_dir() -> Path:
    """Where self-test verdicts are kept: ``$XDG_CACHE_HOME/ucad-cl/selftest`` (default
    ``~/.cache``). Delete it to test every device again."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "ucad-cl" / "selftest"


def program_cache_dir() -> Path:
    """Where built programs' binaries are kept (``Runtime.build_source``):
    ``$XDG_CACHE_HOME/ucad-cl/programs`` (default ``~/.cache``), at most ``PROGRAM_CACHE_FILES``
    (the oldest are deleted). Deleting it costs only the next builds' time."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "ucad-cl" / "programs"


def _status_key(info: DeviceInfo) -> str:
    h = hashlib.sha256(json.dumps([info.platform, info.device, info.driver]).encode())
    h.update(" ".join(abi.defines()).encode())
    pkg = resources.files("ucad_cl")
    for name in SELF_TEST_SOURCES:
        h.update((pkg / name).read_bytes())
    for p in sorted(resources.files("ucad_cl.kernels").iterdir(), key=lambda p: p.name):
        if p.name.endswith((".cl", ".h")):
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()[:32]


def create_unchecked_runtime(spec: str) -> Runtime:
    """A runtime on exactly the device ``spec`` names, without the self-test (what the
    self-test itself runs on; anything else uses ``create_runtime``)."""
    import pyopencl as cl

    info, dev = _match(spec, _devices())
    ctx = cl.Context([dev])
    return Runtime(ctx=ctx, queue=cl.CommandQueue(ctx), device=dev, info=info,
                   why="self-test: no choice made")


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
    """Human-readable list of every OpenCL device and its self-test verdict:
    ``"P:D  usable    platform | device | PoCL ..."`` or ``"P:D  unusable  ... -- reason"``."""
    out = []
    for st in device_report():
        verdict = "usable  " if st.usable else "unusable"
        out.append(f"{st.info.spec}  {verdict}  {st.info.summary()}"
                   + ("" if st.usable else f" -- {st.reason}"))
    return out


def device_report(checks: tuple[str, ...] | None = None) -> list[DeviceStatus]:
    """The self-test verdict of every OpenCL device, in platform / device order (``checks``:
    see ``device_status``)."""
    return [device_status(info, checks=checks) for info in device_infos()]


def usable_device_specs() -> list[str]:
    """Specs ("P:D") of every device that passes the self-test, best first."""
    usable = [st.info for st in device_report() if st.usable]
    return [i.spec for i in sorted(usable, key=device_rank)]


def device_infos() -> list[DeviceInfo]:
    """``DeviceInfo`` of every OpenCL device, in platform / device order (no context made)."""
    return [info for info, _ in _devices()]


def _devices() -> list[tuple[DeviceInfo, Any]]:
    """(DeviceInfo, pyopencl.Device) of every OpenCL device, in platform / device order."""
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except Exception as exc:  # pyopencl raises LogicError/RuntimeError without an ICD
        first = (str(exc).strip().splitlines() or [""])[0]
        raise OpenCLUnavailable(f"no OpenCL platform (pyopencl: {first}); {INSTALL_HINT}"
                                ) from exc
    return [(device_info(f"{pi}:{di}", p, d), d)
            for pi, p in enumerate(platforms) for di, d in enumerate(p.get_devices())]


def slow_device_warning(info: DeviceInfo | None) -> str | None:
    """The warning to print when ``info`` is a device known to be slow, else None."""
    reason = info.slow_reason() if info is not None else None
    if info is None or reason is None:
        return None
    return (f"warning: OpenCL device {info.spec} ({info.device}): {reason}; {SLOW_POCL_COST}. "
            f"Fix: {INSTALL_FAST}.")
