"""``ucad-index info``: version, OpenCL platforms/devices and the device in use, and why."""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser("info", help="show the OpenCL devices, which are usable, the one in use "
                                    "and why",
                       description="List every OpenCL platform/device (for PoCL: its version, "
                                   "LLVM version and the CPU its kernels are compiled for), "
                                   "usable or unusable with the reason: a device is usable when "
                                   "it passes the self-test (every kernel built and created, a "
                                   "small render, Canny and search checked against NumPy and "
                                   "OpenCV, run in a child process and cached per device, driver "
                                   "and kernel sources). Then the one ucad-index uses and why: "
                                   "the best usable device (a GPU, then PoCL on the CPU: a "
                                   "named-CPU target before the generic x86-64 one, then the "
                                   "newer PoCL and LLVM); a device known to be slow is flagged "
                                   "with the measured cost and the fix. Select another with "
                                   "--device P:D or a name substring (or UCAD_CL_DEVICE).")
    p.set_defaults(func=run)


def run(args) -> int:
    from .. import __version__
    from ..runtime import OpenCLUnavailable, get_runtime, list_devices, slow_device_warning

    print(f"ucad-index {__version__}")
    try:
        for line in list_devices():
            print("  " + line)
        rt = get_runtime()
        print(f"in use: {rt.info.spec if rt.info else ''} {rt.describe()}")
        print(f"why: {rt.why}")
        warning = slow_device_warning(rt.info)
        if warning:
            print(warning, file=sys.stderr)
    except OpenCLUnavailable as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
