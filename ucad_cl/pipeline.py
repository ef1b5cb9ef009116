"""The per-mesh pipeline of a build: the stages from a library file to a ``CatalogEntry``, and
the artifact serialisers. The engines (``ucad_cl.engines``) load it in their worker processes
only; the driver (``ucad_cl.build``) commits what it returns. Options, mesh references and
rejections are ``ucad_cl.jobs`` (no stage imports, so the driver stays small).

``Pipeline(options).identify(ref)`` -> content key (or a rejection when the file cannot be read);
``.load_entry(ref, sha)`` -> the mesh (ingest, under the worker's limits) or a rejection;
``.process_entry(ref, mesh, seconds, staging)`` -> ingest -> [decimate] -> filter -> render ->
filter by views -> edges -> segment -> classify (+ curators' label overrides) -> features ->
``CatalogEntry``. Artifacts go to ``staging`` (EXR) or stay bytes; their kinds are
``ucad_catalog._db.ARTIFACT_KINDS``.

Rings: every stored ring (``BuildOptions.elevations``) is rendered, written and described
(features); the *label ring*, the first elevation's views (stored first, so their indices are the
stack's), is what the view filter, the edges, the segmenter, the classifier and the parts sheet
see. The default stores 15 deg (the label ring) then 5 deg (for retrieval and pose of photos
taken from low down, docs/FIT.md), so labels are those of a 15 deg ring alone.

The loader is a seam: ``Pipeline(options, loader=...)`` replaces ``ingest.load_mesh`` (a picklable
module-level function ``loader(path, *, budgets, orientation) -> Mesh``; the pipeline orients
the mesh itself, so it passes ``orientation=None``), so tests can stand in a native reader
that crashes or hangs; ``build(..., loader=...)`` hands it to every worker.
"""
from __future__ import annotations

import gzip
import io
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ucad_catalog.entry import CatalogEntry
from ucad_catalog.exr import write_viewset_exr

from .artifacts import Verdict
from .cameras import label_ring, make_ring
from .classify import classify_parts
from .curation import LabelOverrides, apply_label_overrides
from .decimate import decimate
from .edges import material_edges
from .features import HogExtractor, view_features
from .filter import filter_mesh, filter_views
from .ingest import IngestError, describe_exception, load_mesh, mesh_identity, unreadable_identity
from .jobs import BuildOptions, MeshRef, environment_code, rejected_entry
from .orient import OrientationOverrides, orient_mesh
from .pose import box_side
from .render import render_views
from .runtime import Runtime
from .names import name_priors
from .segment import segmenter_from_spec
from .shade import shade_views
from .sheets import part_sheet


class Pipeline:
    """The per-mesh stages with their state (segmenter, feature extractor) built once; every
    device step runs on ``runtime`` (default: the process's, ``get_runtime()``)."""

    def __init__(self, options: BuildOptions, loader: Callable | None = None,
                 runtime: Runtime | None = None):
        self.options = options
        self.runtime = runtime
        self.loader = loader or load_mesh
        self.budgets = options.budgets()
        self.overrides = OrientationOverrides(dict(options.orientation_overrides))
        self.labels = LabelOverrides.from_items(options.label_overrides)
        self.ring = make_ring(azimuth_step=options.azimuth_step, elevations=options.elevations,
                              fov_deg=options.fov_deg, size=options.size)
        self.label_views = label_ring(self.ring)
        self.segmenter = segmenter_from_spec(options.segmenter, runtime)
        self.extractor = None
        if options.features:
            self.extractor = HogExtractor(runtime=runtime)

    def identify(self, ref: MeshRef) -> tuple[str, object]:
        """(content key, None), or (key, rejected CatalogEntry) when the file cannot be read."""
        try:
            return mesh_identity(ref.path, self.budgets), None
        except IngestError as exc:
            sha = unreadable_identity(ref.path)
            return sha, rejected_entry(ref, sha, exc.reason, str(exc))

    def load(self, ref: MeshRef):
        """Ingest, then orient (may raise IngestError or MemoryError). Returns (mesh,
        {stage: seconds})."""
        t0 = time.perf_counter()
        mesh = self.loader(ref.path, budgets=self.budgets, orientation=None)
        t1 = time.perf_counter()
        mode = self.overrides.mode_for(ref.path, mesh.sha256, self.options.orientation)
        mesh = orient_mesh(mesh, mode)
        return mesh, {"ingest": t1 - t0, "orient": time.perf_counter() - t1}

    def load_entry(self, ref: MeshRef, sha: str):
        """``load`` with every input fault turned into a rejected entry: (mesh, {stage: seconds},
        None) or (None, {}, entry). MemoryError passes through (the caller attributes it)."""
        try:
            mesh, secs = self.load(ref)
            return mesh, secs, None
        except IngestError as exc:
            return None, {}, rejected_entry(ref, sha, exc.reason, str(exc))
        except MemoryError:
            raise
        except Exception as exc:             # a reader quirk on a strange file: an input fault
            return None, {}, rejected_entry(ref, sha, "unreadable",
                                             f"{ref.path}: {describe_exception(exc)}")

    def process(self, ref: MeshRef, mesh, load_seconds: dict, staging: Path):
        """Everything after ingest; returns a CatalogEntry (accepted or rejected).
        ``load_seconds``: ``{stage: seconds}`` from ``load``."""
        o = self.options
        timings = dict(load_seconds)
        t = time.perf_counter()
        notes = "; ".join(mesh.report.notes)

        def lap(name):
            nonlocal t
            now = time.perf_counter()
            timings[name] = timings.get(name, 0.0) + now - t
            t = now

        def rejected(verdict):
            if notes:
                verdict = Verdict(False, verdict.reason, f"{verdict.detail} ({notes})")
            return CatalogEntry.from_results(sha256=mesh.sha256, path=ref.path, size=ref.size,
                                             mtime=ref.mtime, verdict=verdict, mesh=mesh,
                                             timings=timings)

        orient = mesh.orientation
        if o.reject_uncertain_orientation and orient is not None and orient.uncertain:
            return rejected(Verdict(False, "uncertain_orientation",
                                    f"{ref.path}: orientation confidence up "
                                    f"{orient.up_confidence:.2f}, front "
                                    f"{orient.front_confidence:.2f} (flags: "
                                    f"{', '.join(orient.flags) or 'none'})"))
        if o.triangle_budget and mesh.n_faces > o.triangle_budget:
            mesh = decimate(mesh, o.triangle_budget)
            lap("decimate")
        verdict = filter_mesh(mesh, min_materials=o.min_materials, max_triangles=o.max_triangles)
        lap("filter")
        if not verdict.accepted:
            return rejected(verdict)
        views = render_views(mesh, self.ring, runtime=self.runtime)
        labelled = views.select(self.label_views)          # the label ring (module docstring)
        lap("render")
        verdict = filter_views(mesh, labelled, dominant_fraction=o.dominant_fraction,
                               min_visible_materials=o.min_visible_materials)
        lap("filter")
        if not verdict.accepted:
            return rejected(verdict)
        artifacts = {}
        staging.mkdir(parents=True, exist_ok=True)
        exr = staging / f"{mesh.sha256}.views.exr"
        write_viewset_exr(exr, views, mesh)
        artifacts["views.exr"] = exr
        lap("write")
        if o.edges:
            edges = material_edges(labelled, runtime=self.runtime).edges
            artifacts["edges.npy.gz"] = npy_gz_bytes(np.packbits(edges > 0, axis=-1))
            lap("edges")
        masks = self.segmenter.segment(mesh, labelled)
        lap("segment")
        table = classify_parts(mesh, labelled, masks, threshold=o.threshold,
                               priors=name_priors(mesh), runtime=self.runtime)
        fixes = self.labels.for_mesh(ref.path, mesh.sha256)
        if fixes:                                   # curators' corrections win (curation.py)
            table, missing = apply_label_overrides(table, mesh, fixes)
            notes = "; ".join(n for n in [notes, *missing] if n)
        lap("classify")
        if self.extractor is not None:
            images = shade_views(mesh, views, background=(128, 128, 128), runtime=self.runtime)
            feats = view_features(self.extractor, images, views).feats
            artifacts["features.npy"] = npy_bytes(feats.astype(np.float32))
            lap("features")
        artifacts["parts.png"] = parts_sheet_png(labelled, table)
        lap("write")
        visible = views.material_counts()[:, 1:].sum(axis=1)
        view_stats = [{"visible_pixels": int(visible[v]),
                       "box_side": float(box_side(views.mat_id[v] > 0))}
                      for v in range(views.n_views)]
        return CatalogEntry.from_results(
            sha256=mesh.sha256, path=ref.path, size=ref.size, mtime=ref.mtime,
            verdict=Verdict(True, "", notes), mesh=mesh, table=table, ring=self.ring,
            artifacts=artifacts, timings=timings, view_stats=view_stats)

    def process_entry(self, ref: MeshRef, mesh, load_seconds: dict, staging: Path):
        """``process`` with an unexpected error recorded as ``pipeline_error``. Environment
        faults (``environment_code``) and MemoryError pass through."""
        try:
            return self.process(ref, mesh, load_seconds, staging)
        except MemoryError:
            raise
        except Exception as exc:
            if environment_code(exc):
                raise
            return rejected_entry(ref, mesh.sha256, "pipeline_error",
                                  f"{ref.path}: {describe_exception(exc)}")


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def npy_gz_bytes(a: np.ndarray) -> bytes:
    """Deterministic gzip (mtime 0) of an .npy file. Level 1: a mesh's packed edge maps in 2 ms
    (56 kB) instead of 6 ms (44 kB) at level 6."""
    return gzip.compress(npy_bytes(a), compresslevel=1, mtime=0)


def parts_sheet_png(views, table) -> bytes:
    """Contact sheet of (at most 24 of) the views coloured by part, as PNG bytes."""
    import cv2

    sub = views.select(slice(0, views.n_views, max(1, views.n_views // 24)))  # views, no copy
    ok, png = cv2.imencode(".png", cv2.cvtColor(part_sheet(sub, table, 1600), cv2.COLOR_RGB2BGR))
    return png.tobytes()
