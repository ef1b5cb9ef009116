"""Shared fixtures: one OpenCL runtime per session, paths to the shared real vehicle models."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VEHICLES = ROOT.parent / "shared" / "data" / "vehicles"


@pytest.fixture(scope="session")
def runtime():
    from ucad_cl.runtime import get_runtime
    return get_runtime()


@pytest.fixture(scope="session")
def vehicles_dir():
    if not (VEHICLES / "manifest.json").exists():
        pytest.skip(f"shared vehicle models not found at {VEHICLES}")
    return VEHICLES
