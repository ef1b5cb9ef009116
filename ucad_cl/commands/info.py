"""``ucad-index info``: version, OpenCL platforms/devices and the device in use."""
from __future__ import annotations

import sys


def register(sub) -> None:
    p = sub.add_parser("info", help="show the OpenCL devices and the one in use",
                       description="List every OpenCL platform/device and show which one ucad-index "
                                   "uses (select with --device or UCAD_CL_DEVICE).")
    p.set_defaults(func=run)


def run(args) -> int:
    from .. import __version__
    from ..runtime import OpenCLUnavailable, get_runtime, list_devices

    print(f"ucad-index {__version__}")
    try:
        for line in list_devices():
            print("  " + line)
        print(f"in use: {get_runtime().describe()}")
    except OpenCLUnavailable as exc:
        print(str(exc), file=sys.stderr)
        return 2
    return 0
