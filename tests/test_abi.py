"""The kernel ABI (ucad_cl/abi.py) against the kernels, on every test device: each parameter
struct's NumPy dtype has the C struct's size, field offsets and field sizes (read back from a
probe kernel compiled with the kernel file's own source), and the -D constants reach the kernels.
"""
from __future__ import annotations

import re

import numpy as np
import pytest

from ucad_cl import abi
from ucad_cl.runtime import kernel_source

pytestmark = pytest.mark.every_device      # tests/conftest.py: UCAD_TEST_DEVICES


def c_layout(runtime, struct: abi.Struct, fields, source: str | None = None):
    """(sizeof, [(offset, size) per field]) of ``struct`` as the device compiles it; ``source``
    replaces the kernel file's text (to show a one-sided change is caught)."""
    import pyopencl as cl

    src = kernel_source(struct.program) if source is None else source
    t = struct.c_name
    lines = [f"    out[0] = sizeof({t});"]
    for i, f in enumerate(fields):
        lines.append(f"    out[{1 + 2 * i}] = __builtin_offsetof({t}, {f});")
        lines.append(f"    out[{2 + 2 * i}] = sizeof((({t} *)0)->{f});")
    probe = "kernel void ucad_abi_probe(global ulong *out) {\n" + "\n".join(lines) + "\n}\n"
    prg = cl.Program(runtime.ctx, src + "\n" + probe).build(
        options=["-cl-std=CL1.2", *abi.defines()])
    out = np.zeros(1 + 2 * len(fields), np.uint64)
    buf = cl.Buffer(runtime.ctx, cl.mem_flags.WRITE_ONLY, out.nbytes)
    prg.ucad_abi_probe(runtime.queue, (1,), (1,), buf)
    cl.enqueue_copy(runtime.queue, out, buf)
    runtime.queue.finish()
    return int(out[0]), [(int(out[1 + 2 * i]), int(out[2 + 2 * i])) for i in range(len(fields))]


def layout_mismatches(runtime, struct: abi.Struct, source: str | None = None) -> list[str]:
    """What differs between ``struct.dtype`` and the C struct (empty: they agree)."""
    import pyopencl as cl

    dt = struct.dtype
    try:
        size, offs = c_layout(runtime, struct, dt.names, source)
    except cl.RuntimeError as e:                    # e.g. a dtype field the C struct lacks
        missing = [f for f in dt.names if re.search(rf"no member named '{f}'", str(e))]
        return [f"{struct.c_name}: C struct has no field {missing or '?'} ({struct.program}.cl)"]
    bad = [] if size == dt.itemsize else [
        f"{struct.c_name}: sizeof {size} in {struct.program}.cl, itemsize {dt.itemsize} in abi.py"]
    for name, (off, fsize) in zip(dt.names, offs):
        want = (dt.fields[name][1], dt.fields[name][0].itemsize)
        if (off, fsize) != want:
            bad.append(f"{struct.c_name}.{name}: offset/size {(off, fsize)} in C, {want} in abi.py")
    return bad


@pytest.mark.parametrize("struct", abi.STRUCTS, ids=lambda s: f"{s.program}.{s.c_name}")
def test_struct_dtypes_match_the_kernels(runtime, struct):
    assert layout_mismatches(runtime, struct) == []


def test_a_field_added_on_one_side_only_is_caught(runtime):
    raster = abi.STRUCTS[0]
    # on the C side only: a new last field changes sizeof
    src = kernel_source(raster.program)
    grown = src.replace("    uint big_capacity;\n} raster_params;",
                        "    uint big_capacity;\n    int extra;\n} raster_params;")
    assert grown != src
    assert any("sizeof 28" in m for m in layout_mismatches(runtime, raster, grown))
    # on the C side only, inside the struct: offsets move
    moved = src.replace("    float near;\n", "    int first_row;\n    float near;\n")
    assert moved != src and layout_mismatches(runtime, raster, moved)
    # on the NumPy side only: the C struct has no such member
    extra = abi.Struct(raster.program, raster.c_name,
                       np.dtype(raster.dtype.descr + [("extra", np.int32)]))
    assert layout_mismatches(runtime, extra) == [
        f"raster_params: C struct has no field ['extra'] ({raster.program}.cl)"]


def test_constants_reach_the_kernels_as_defines(runtime):
    import pyopencl as cl

    names = list(abi.CONSTANTS)
    body = "\n".join(f"    out[{i}] = (long)({n});" for i, n in enumerate(names))
    src = kernel_source("shade") + "\nkernel void ucad_abi_consts(global long *out) {\n" + body + "\n}\n"
    prg = cl.Program(runtime.ctx, src).build(options=["-cl-std=CL1.2", *abi.defines()])
    out = np.zeros(len(names), np.int64)
    buf = cl.Buffer(runtime.ctx, cl.mem_flags.WRITE_ONLY, out.nbytes)
    prg.ucad_abi_consts(runtime.queue, (1,), (1,), buf)
    cl.enqueue_copy(runtime.queue, out, buf)
    runtime.queue.finish()
    want = [abi.BG_TRI, abi.BG_MAT, abi.BIG_PIXELS, abi.MAX_BINS, abi.K_MAX, abi.SRGB_BUCKETS,
            abi.MAX_PARTS]
    assert out.tolist() == want


def test_a_build_without_the_defines_fails_clearly(runtime):
    import pyopencl as cl

    with pytest.raises(cl.RuntimeError, match="ABI defines"):
        cl.Program(runtime.ctx, kernel_source("shade")).build(options=["-cl-std=CL1.2"])


def test_every_kernel_file_builds_through_the_runtime(runtime):
    from importlib import resources
    files = sorted(p.name[:-3] for p in resources.files("ucad_cl.kernels").iterdir()
                   if p.name.endswith(".cl"))
    assert {"raster_parallel", "raster_serial", "canny", "shade", "parts", "features",
            "search"} <= set(files)
    for name in files:
        assert runtime.program(name) is not None
    assert {s.program for s in abi.STRUCTS} <= set(files)
