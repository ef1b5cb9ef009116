"""The device self-test (ucad_cl/selftest.py) and what it decides (ucad_cl/runtime.py): a device
is usable only if it runs this project's kernels correctly; a broken one is excluded with its
reason, found in a child process that may crash without harming the caller.

The failures are built for real on the device under test: a program that builds but declares a
kernel that cannot be created (what PyPI's PoCL 3.0 does on an AMD Zen 4: INVALID_KERNEL_NAME), a
kernel that returns wrong results, a child that aborts, and one that answers and then aborts at
exit (LLVM's "still have references to IRs"). The check functions below run in the child."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ucad_cl.runtime import (OpenCLUnavailable, create_runtime, device_infos, device_report,
                             device_status, get_runtime, self_test_cache_dir,
                             usable_device_specs)
from ucad_cl.selftest import SelfTestFailed, check_program, kernel_names

HERE = "tests.test_selftest"


# ------------------------------------------------------------- checks run in the child process
def check_uncreatable_kernel(rt) -> None:
    """A program that builds, and declares a kernel the build does not contain."""
    check_program(rt, "ghost.cl", "kernel void real_one(global int *a) { a[0] = 1; }\n"
                                  "#if 0\nkernel void ghost(global int *a) { a[0] = 2; }\n#endif\n")


def check_wrong_results(rt) -> None:
    """A kernel whose result differs from NumPy's in one element (a device computing wrong)."""
    prg = rt.build_source("kernel void add(global const float *a, global const float *b, "
                          "global float *c) { int i = get_global_id(0); "
                          "c[i] = a[i] + b[i] + (i == 7 ? 1.0f : 0.0f); }")
    a = np.arange(16, dtype=np.float32)
    b = np.full(16, 0.5, np.float32)
    bad = np.flatnonzero(_add(rt, prg, a, b) != a + b)
    if bad.size:
        raise SelfTestFailed(f"add: {bad.size} of 16 sums differ from NumPy")


def _add(rt, prg, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``prg``'s kernel ``add(a, b, c)`` run over float32 ``a`` and ``b``: c."""
    import pyopencl as cl

    mf = cl.mem_flags
    da = cl.Buffer(rt.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
    db = cl.Buffer(rt.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=b)
    dc = cl.Buffer(rt.ctx, mf.WRITE_ONLY, a.nbytes)
    prg.add(rt.queue, a.shape, None, da, db, dc)
    c = np.empty_like(a)
    cl.enqueue_copy(rt.queue, c, dc)
    return c


def check_aborts(rt) -> None:
    os.abort()


def check_aborts_at_exit(rt) -> None:
    import atexit
    atexit.register(os.abort)


# ------------------------------------------------------------------------------------- tests
@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A fresh verdict cache (the self-test's children inherit the variable). PoCL keeps its
    compiled kernels where it did (``POCL_CACHE_DIR``; by default it follows XDG_CACHE_HOME):
    the verdicts are under test, not PoCL's compiler (an empty kernel cache cost this file
    30-120 s on a 2-core Zen 4)."""
    if "POCL_CACHE_DIR" not in os.environ:
        home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        monkeypatch.setenv("POCL_CACHE_DIR", os.path.join(home, "pocl", "kcache"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_kernel_names_parses_declarations():
    src = ("__kernel void a(global int *x) {}\n"
           "kernel __attribute__((reqd_work_group_size(8, 1, 1))) void b_2 (int y) {}\n"
           "void not_a_kernel(void) {}\n")
    assert kernel_names(src) == ["a", "b_2"]


def test_every_usable_device_passes_and_the_verdict_is_cached(cache):
    info = get_runtime().info
    first = device_status(info, refresh=True)
    assert first.usable and first.reason == "" and not first.cached and first.seconds > 0
    again = device_status(info)
    assert again.usable and again.cached
    files = list(self_test_cache_dir().glob("*.json"))
    assert len(files) == 1 and json.loads(files[0].read_text())["usable"] is True
    assert info.spec in usable_device_specs()


@pytest.mark.parametrize("check, reason", [
    ("check_uncreatable_kernel", "kernels: ghost.cl builds but kernel 'ghost' cannot be created"),
    ("check_wrong_results", "add: 1 of 16 sums differ from NumPy"),
    ("check_aborts", "the self-test's process died (killed by signal SIGABRT)"),
    ("check_aborts_at_exit", "the self-test's process answered, then died at exit (killed by "
                             "signal SIGABRT)"),
])
def test_broken_devices_are_excluded_with_their_reason(cache, check, reason):
    rt = get_runtime()
    checks = (f"{HERE}:{check}",)
    report = device_report(checks=checks)
    mine = [st for st in report if st.info.spec == rt.info.spec]
    assert len(mine) == 1 and not mine[0].usable
    assert mine[0].reason.startswith(reason), mine[0].reason
    assert "\n" not in mine[0].reason
    assert not list(cache.glob("**/*.json"))           # other checks are never cached
    # the caller is unharmed: its runtime still renders, and the real suite still passes
    assert device_status(rt.info).usable


def test_no_usable_device_is_one_line_naming_what_to_install(cache, tmp_path, monkeypatch):
    """Every device marked unusable in the cache: `info` lists each with its reason and exits 2,
    a command that needs OpenCL prints one line naming what to install; no traceback."""
    env = {**os.environ, "XDG_CACHE_HOME": str(cache)}
    env.pop("UCAD_CL_DEVICE", None)
    for info in device_infos():
        device_status(info)                               # fill the cache ...
    for f in self_test_cache_dir().glob("*.json"):        # ... and mark every device broken
        rec = json.loads(f.read_text())
        f.write_text(json.dumps({**rec, "usable": False, "reason": "kernels: simulated"}))
    monkeypatch.delenv("UCAD_CL_DEVICE", raising=False)
    assert usable_device_specs() == []
    with pytest.raises(OpenCLUnavailable, match="no usable OpenCL device"):
        create_runtime()
    cli = [str(Path(sys.executable).parent / "ucad-index")]
    info = subprocess.run([*cli, "info"], env=env, capture_output=True, text=True, timeout=120)
    assert info.returncode == 2
    assert info.stdout.count("unusable") == len(device_infos())
    assert "kernels: simulated" in info.stdout
    err = info.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: no usable OpenCL device")
    assert "apt-get install pocl-opencl-icd" in err[0]
    mesh = tmp_path / "tri.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    run = subprocess.run([*cli, "render", str(mesh), "--out", str(tmp_path / "r")], env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert run.stderr.strip().splitlines()[-1].startswith("error: no usable OpenCL device")
    # a device named explicitly is refused with the self-test's reason, in one line
    spec = device_infos()[0].spec
    named = subprocess.run([*cli, "--device", spec, "info"], env=env, capture_output=True,
                           text=True, timeout=120)
    assert named.returncode == 2
    assert f"OpenCL device {spec}" in named.stderr and "kernels: simulated" in named.stderr


def test_correctly_rounded_division_only_where_the_device_offers_it(monkeypatch, tmp_path):
    """Every program's options come from ``Runtime.build_source``: it asks for correctly
    rounded float division and sqrt only on a device whose single-precision config has
    CL_FP_CORRECTLY_ROUNDED_DIVIDE_SQRT (the OpenCL specification allows the option nowhere
    else), and no kernel module asks for it itself: the rasteriser's and the shading's
    programs get the same options as the others."""
    import pyopencl as cl

    from ucad_cl.runtime import Runtime

    seen: list[list[str]] = []

    class Program:
        def __init__(self, ctx, source):
            pass

        def build(self, options):
            seen.append(list(options))
            return self

        def get_info(self, what):
            return [b""]                            # no binary: nothing cached

    class Platform:
        name = version = "fake"

    class Device:
        single_fp_config = 0
        platform = Platform()
        name = version = driver_version = "fake"

    monkeypatch.setattr(cl, "Program", Program)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    flag = "-cl-fp32-correctly-rounded-divide-sqrt"
    rt = Runtime(ctx=None, queue=None, device=Device())
    rt.build_source("kernel void k(void) {}")
    assert flag not in seen[-1] and "-cl-std=CL1.2" in seen[-1]
    Device.single_fp_config = int(cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT)
    for name in ("raster_serial", "shade", "features"):
        rt.program(name)
        assert seen[-1].count(flag) == 1, (name, seen[-1])


def test_no_kernel_module_passes_the_rounding_option_itself(runtime):
    """Renders through both raster paths and their shading on the session's device: no program
    was built with the correctly-rounded option among its own options
    (``Runtime.compile_seconds`` keys: name, options); ``build_source`` adds it where the device
    offers it. (Both paths asked for by name: a GPU's default is the parallel one.)"""
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views
    from ucad_cl.shade import shade_views
    from ucad_cl.synth import make_vehicle

    mesh = make_vehicle(1, "sedan").mesh()
    names = ("raster_serial", "raster_parallel", "shade")
    for path in ("serial", "parallel"):
        views = render_views(mesh, make_ring(90.0, (10.0,), size=(64, 48)), runtime=runtime,
                             path=path)
        shade_views(mesh, views, runtime=runtime)
    built = [key for key in runtime.compile_seconds if key[0] in names]
    assert {k[0] for k in built} == set(names), built
    assert not any("-cl-fp32-correctly-rounded-divide-sqrt" in opts for _, opts in built)


SUM_KERNEL = ("kernel void add(global const float *a, global const float *b, global float *c) "
              "{ int i = get_global_id(0); c[i] = (a[i] + b[i]) * 2.0f; }")


def _run_add(rt, prg) -> None:
    a = np.linspace(-1, 1, 64, dtype=np.float32)
    b = np.linspace(2, 5, 64, dtype=np.float32)
    assert np.array_equal(_add(rt, prg, a, b), (a + b) * np.float32(2.0))


def test_program_binaries_cached_on_disk(runtime, tmp_path, monkeypatch):
    """``Runtime.build_source`` keeps each built program's binary (``program_cache_dir``) and
    builds from it next time (the driver is handed the binary, not the source); a binary whose
    bytes were damaged is refused by its checksum and built from source again (and cached
    anew); programs from the binary compute what NumPy does and render the same bytes as from
    source; at most ``PROGRAM_CACHE_FILES`` are kept, the newest."""
    import pyopencl as cl

    from ucad_cl import runtime as rtm
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views
    from ucad_cl.synth import make_vehicle

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    folder = rtm.program_cache_dir()
    built = []
    real = cl.Program

    def spy(ctx, *args):
        built.append("binary" if len(args) == 2 else "source")
        return real(ctx, *args)

    monkeypatch.setattr(cl, "Program", spy)
    _run_add(runtime, runtime.build_source(SUM_KERNEL))
    assert built == ["source"] and len(list(folder.glob("*.bin"))) == 1
    _run_add(runtime, runtime.build_source(SUM_KERNEL))
    assert built[1:] == ["binary"]
    (path,) = folder.glob("*.bin")
    blob = bytearray(path.read_bytes())
    blob[len(blob) // 2] ^= 0xFF                   # a damaged binary
    path.write_bytes(bytes(blob))
    _run_add(runtime, runtime.build_source(SUM_KERNEL))
    assert built[2:] == ["source"]
    _run_add(runtime, runtime.build_source(SUM_KERNEL))
    assert built[3:] == ["binary"]                 # cached anew

    mesh = make_vehicle(3, "suv").mesh()
    ring = make_ring(60.0, (10.0,), size=(64, 48))
    fresh = [rtm.Runtime(ctx=runtime.ctx, queue=runtime.queue, device=runtime.device)
             for _ in range(2)]
    del built[:]
    first = render_views(mesh, ring, runtime=fresh[0])
    again = render_views(mesh, ring, runtime=fresh[1])
    assert built == ["source", "binary"]
    for name in ("tri_id", "mat_id", "depth"):
        assert getattr(first, name).tobytes() == getattr(again, name).tobytes(), name

    monkeypatch.setattr(rtm, "PROGRAM_CACHE_FILES", 2)
    for k in range(3):
        runtime.build_source(f"{SUM_KERNEL}\n// variant {k}")
    assert len(list(folder.glob("*.bin"))) == 2


def test_a_successful_build_says_nothing(runtime, tmp_path, monkeypatch):
    """pyopencl warns (``CompilerWarning``) at every build whose log is not empty, and Debian's
    PoCL for 'haswell' logs ABI notes at every build of our programs, so every ``ucad-index``
    call printed two lines of it: a build that succeeds leaves no warning for the user, from
    source and from the cached binary; with pyopencl's ``PYOPENCL_COMPILER_OUTPUT`` set the
    log is shown as pyopencl shows it; a program that does not build still raises. (Device logs
    are not reliable enough to test on: the build here warns as pyopencl does for a log.)"""
    import warnings

    import pyopencl as cl

    real = cl.Program

    class Noisy:
        def __init__(self, *args):
            self.prg = real(*args)

        def build(self, **kw):
            built = self.prg.build(**kw)
            warnings.warn("From-source build succeeded, but resulted in non-empty logs",
                          cl.CompilerWarning, stacklevel=2)
            return built

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("PYOPENCL_COMPILER_OUTPUT", raising=False)
    monkeypatch.setattr(cl, "Program", Noisy)
    for _ in range(2):                                  # from source, then from the binary
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            _run_add(runtime, runtime.build_source(SUM_KERNEL + "// noisy"))
        assert not [w for w in seen if issubclass(w.category, cl.CompilerWarning)]
    monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "1")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        runtime.build_source(SUM_KERNEL + "// noisy")
    assert [w for w in seen if issubclass(w.category, cl.CompilerWarning)]
    monkeypatch.setattr(cl, "Program", real)
    with pytest.raises(cl.Error):
        runtime.build_source(SUM_KERNEL + "\nkernel void broken(void) { undeclared = 1; }\n")
