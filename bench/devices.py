"""Run a bench once per PoCL build present and print the results side by side.

``bench/search.py`` and ``bench/edges.py`` call ``per_device(...)`` first: without ``--device``
(and without ``UCAD_CL_DEVICE``), when several PoCL CPU devices are installed (e.g. Debian's
PoCL 3.1 and the PyPI wheel's 3.0), the script re-runs itself in one subprocess per device with
``--device P:D --json FILE`` and then prints one comparison table; each subprocess prints its own
full table too. With one device, or ``--device``, it runs in-process as before.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile


def pocl_devices() -> list:
    """``DeviceInfo`` of every PoCL device (``ucad_cl.runtime.device_infos``), best first."""
    from ucad_cl.runtime import OpenCLUnavailable, device_infos, device_rank

    try:
        return sorted((i for i in device_infos() if i.is_pocl), key=device_rank)
    except OpenCLUnavailable:
        return []


def per_device(argv: list[str], device: str | None) -> list[tuple[object, dict]] | None:
    """None when this process should run the bench itself (one device, or --device given);
    else [(DeviceInfo, results dict)] of one subprocess per PoCL device."""
    if device or os.environ.get("UCAD_CL_DEVICE"):
        os.environ["UCAD_CL_DEVICE"] = device or os.environ["UCAD_CL_DEVICE"]
        return None
    devices = pocl_devices()
    if len(devices) < 2:
        return None
    out = []
    for info in devices:
        print(f"\n===== {info.spec}: {info.summary()}", flush=True)
        with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
            path = f.name
        env = dict(os.environ, UCAD_CL_DEVICE=info.spec)
        run = subprocess.run([sys.executable, sys.argv[0], *argv, "--device", info.spec,
                              "--json", path], env=env)
        try:
            with open(path) as fh:
                results = json.load(fh) if run.returncode == 0 else {}
        except (OSError, json.JSONDecodeError):
            results = {}
        os.unlink(path)
        out.append((info, results))
    return out


def side_by_side(runs: list[tuple[object, dict]], unit: str) -> None:
    """One row per measured case: throughput on each device and the ratio to the first."""
    if not runs or not runs[0][1]:
        print("\n(no results to compare)")
        return
    names = [info.spec for info, _ in runs]
    print(f"\nside by side ({unit}, medians; same run, same machine):")
    print(f"{'case':40s} " + " ".join(f"{n:>12s}" for n in names)
          + " " + " ".join(f"{names[0] + '/' + n:>12s}" for n in names[1:]))
    for case, first in runs[0][1].items():
        row = [r.get(case) for _, r in runs]
        cells = " ".join(f"{v:12.0f}" if v else f"{'-':>12s}" for v in row)
        ratios = " ".join(f"{first / v:12.2f}" if v else f"{'-':>12s}" for v in row[1:])
        print(f"{case:40s} {cells} {ratios}")
    for info, _ in runs:
        print(f"  {info.spec}: {info.summary()}")
