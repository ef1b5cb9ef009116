"""``ucad-index info``: version, OpenCL platforms/devices and the device in use, and why."""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser("info", help="show the OpenCL devices, the one in use and why",
                       description="List every OpenCL platform/device (for PoCL: its version, "
                                   "LLVM version and the CPU its kernels are compiled for) and "
                                   "show which one ucad-index uses and why. The default is the "
                                   "best PoCL CPU device that compiles (a named-CPU target before "
                                   "the generic x86-64 one, then the newer PoCL and LLVM); a "
                                   "device known to be slow is flagged with the measured cost "
                                   "and the fix. Select another with --device P:D or a name "
                                   "substring (or UCAD_CL_DEVICE).")
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
        print(str(exc), file=sys.stderr)
        return 2
    return 0
