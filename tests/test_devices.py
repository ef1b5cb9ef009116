"""Outputs are the same bytes on every usable OpenCL device (ucad_cl/runtime.py): a render
through both raster paths, material edges (Canny), the per-part histograms of a generated
vehicle and HOG descriptors (features.cl), compared across every device that passes the
self-test. Skipped where fewer than two usable devices exist (this project's machines have two
PoCL builds; a GPU machine adds one)."""
from __future__ import annotations

import hashlib

import numpy as np
import pytest

from ucad_cl.cameras import make_ring
from ucad_cl.classify import part_histogram
from ucad_cl.edges import material_edges
from ucad_cl.features import HogExtractor
from ucad_cl.render import render_views
from ucad_cl.runtime import create_runtime, usable_device_specs


def _outputs(spec: str) -> dict[str, str]:
    from ucad_cl.synth import make_vehicle

    rt = create_runtime(spec)
    mesh = make_vehicle(3, "sedan").mesh()
    ring = make_ring(azimuth_step=45.0, elevations=(10.0, 35.0), size=(120, 96))
    out = {}
    for path in ("serial", "parallel"):
        v = render_views(mesh, ring, path=path, runtime=rt)
        out[f"render.{path}"] = _digest(v.tri_id, v.mat_id, v.depth)
    edges = material_edges(v, runtime=rt)
    out["edges"] = _digest(edges.edges)
    masks = np.stack([v.mat_id == m for m in (1, 2, 3)], axis=1)
    out["histogram"] = _digest(part_histogram(v.mat_id, masks, runtime=rt))
    crops = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    crops[1] = np.where(v.mat_id[0, :64, :64, None] > 0, 200, 30)    # a silhouette's edges
    out["features"] = _digest(HogExtractor(runtime=rt).describe(crops))
    return out


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def test_outputs_are_identical_on_every_usable_device():
    specs = usable_device_specs()
    if len(specs) < 2:
        pytest.skip(f"fewer than two usable OpenCL devices ({specs})")
    results = {spec: _outputs(spec) for spec in specs}
    first = results[specs[0]]
    for spec in specs[1:]:
        assert results[spec] == first, (specs[0], spec)
