"""Run a bench once per PoCL build present and print the results side by side.

``bench/search.py`` and ``bench/edges.py`` call ``per_device(...)`` first: without ``--device``
(and without ``UCAD_CL_DEVICE``), when several PoCL CPU devices are installed (e.g. Debian's
PoCL 3.1 and the PyPI wheel's 3.0), the script re-runs itself in one subprocess per device with
``--device P:D --json FILE`` and then prints one comparison table. The machine is shared, so the
devices are measured in ``ROUNDS`` alternating rounds (A B A B A B) and the table gives the median
of the rounds per device (each round's own figure is the median of the bench's runs); the first
round's full tables are printed as they come. With one device, or ``--device``, it runs in-process
as before.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

import numpy as np

ROUNDS = 3


def pocl_devices() -> list:
    """``DeviceInfo`` of every PoCL device (``ucad_cl.runtime.device_infos``), best first."""
    from ucad_cl.runtime import OpenCLUnavailable, device_infos, device_rank

    try:
        return sorted((i for i in device_infos() if i.is_pocl), key=device_rank)
    except OpenCLUnavailable:
        return []


def per_device(argv: list[str], device: str | None,
               rounds: int = ROUNDS) -> list[tuple[object, dict]] | None:
    """None when this process should run the bench itself (one device, or --device given);
    else [(DeviceInfo, {case: [value per round]})] from alternating subprocesses per device."""
    if device or os.environ.get("UCAD_CL_DEVICE"):
        os.environ["UCAD_CL_DEVICE"] = device or os.environ["UCAD_CL_DEVICE"]
        return None
    devices = pocl_devices()
    if len(devices) < 2:
        return None
    out = [(info, {}) for info in devices]
    for r in range(rounds):
        for info, results in out:
            with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
                path = f.name
            env = dict(os.environ, UCAD_CL_DEVICE=info.spec)
            cmd = [sys.executable, sys.argv[0], *argv, "--device", info.spec, "--json", path]
            if r == 0:
                print(f"\n===== round 1, {info.spec}: {info.summary()}", flush=True)
                run = subprocess.run(cmd, env=env)
            else:
                print(f"===== round {r + 1}, {info.spec}", flush=True)
                run = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
            try:
                with open(path) as fh:
                    got = json.load(fh) if run.returncode == 0 else {}
            except (OSError, json.JSONDecodeError):
                got = {}
            os.unlink(path)
            for case, value in got.items():
                results.setdefault(case, []).append(value)
    return out


def side_by_side(runs: list[tuple[object, dict]], unit: str) -> None:
    """One row per measured case: throughput on each device and the ratio to the first."""
    if not runs or not runs[0][1]:
        print("\n(no results to compare)")
        return
    names = [info.spec for info, _ in runs]
    done = max(len(v) for _, r in runs for v in r.values())
    print(f"\nside by side ({unit}; median of {done} alternating rounds per device, each round the "
          f"median of its runs; load average now {os.getloadavg()[0]:.1f}):")
    print(f"{'case':40s} " + " ".join(f"{n:>12s}" for n in names)
          + " " + " ".join(f"{names[0] + '/' + n:>12s}" for n in names[1:]))
    for case in runs[0][1]:
        row = [float(np.median(r[case])) if r.get(case) else None for _, r in runs]
        first = row[0]
        cells = " ".join(f"{v:12.0f}" if v else f"{'-':>12s}" for v in row)
        ratios = " ".join(f"{first / v:12.2f}" if v else f"{'-':>12s}" for v in row[1:])
        print(f"{case:40s} {cells} {ratios}")
        print(f"{'  (rounds)':40s} " + " ".join(
            f"{'/'.join(f'{x:.0f}' for x in r.get(case, [])):>12s}" for _, r in runs))
    for info, _ in runs:
        print(f"  {info.spec}: {info.summary()}")
