"""Shared fixtures: the OpenCL runtime(s) under test, paths to the shared real vehicle models.

``runtime`` is the process's default runtime (``get_runtime()``). In modules marked
``pytestmark = pytest.mark.every_device`` (the kernel tests, which pass ``runtime=`` to every
call) it is parametrised instead over the devices ``UCAD_TEST_DEVICES`` names, as pyopencl's
tests follow ``PYOPENCL_TEST``: a comma-separated list of device specs ("0:0", "pocl", see
``ucad_cl.runtime``), or "all" for every device that passes the self-test (``ucad_cl/selftest.py``,
run in a child process, so a broken OpenCL build never runs in the test process); the devices
left out are listed with the reason in the report header. Unset: the default device only.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VEHICLES = ROOT.parent / "shared" / "data" / "vehicles"


def pytest_configure(config):
    config.addinivalue_line("markers", "every_device: run once per device of UCAD_TEST_DEVICES")


def device_specs_under_test() -> list[str | None]:
    """Device specs from ``UCAD_TEST_DEVICES``; [None] (the default device) when unset."""
    value = os.environ.get("UCAD_TEST_DEVICES", "").strip()
    if not value:
        return [None]
    if value.lower() == "all":
        from ucad_cl.runtime import usable_device_specs
        return list(usable_device_specs())
    return [s.strip() for s in value.split(",") if s.strip()]


def pytest_report_header(config):
    """The devices under test, and those UCAD_TEST_DEVICES=all leaves out, with the reason."""
    if os.environ.get("UCAD_TEST_DEVICES", "").strip().lower() != "all":
        return None
    from ucad_cl.runtime import OpenCLUnavailable, device_report
    try:
        report = device_report()
    except OpenCLUnavailable as exc:
        return [f"OpenCL devices: none ({exc})"]
    return [f"OpenCL device {st.info.spec} ({st.info.device}): "
            + ("under test" if st.usable else f"excluded, {st.reason}") for st in report]



def pytest_generate_tests(metafunc):
    if "runtime" in metafunc.fixturenames and metafunc.definition.get_closest_marker(
            "every_device"):
        specs = device_specs_under_test()
        metafunc.parametrize("runtime", specs, indirect=True, scope="session",
                             ids=[f"device={s}" if s else "default" for s in specs])


@pytest.fixture(scope="session")
def runtime(request):
    """The runtime under test (session-scoped: one per device)."""
    from ucad_cl.runtime import create_runtime, get_runtime
    spec = getattr(request, "param", None)
    return get_runtime() if spec is None else create_runtime(spec)


@pytest.fixture(scope="session")
def vehicles_dir():
    if not (VEHICLES / "manifest.json").exists():
        pytest.skip(f"shared vehicle models not found at {VEHICLES}")
    return VEHICLES
