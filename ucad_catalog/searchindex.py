"""The catalogue's search index: every accepted mesh's pose features on their first principal
axes, one derived file ``ROOT/search_index.npz`` that lets a retrieval read a few rows in full
instead of all of them.

Why: a photo's retrieval (``ucad_cl.fit``) compares its HOG with every stored view. Over 1,003
meshes those rows are 72,216 x 1,764 float32 (510 MB) in 1,003 ``features.npy`` objects, and a
process that searches once (one ``ucad-index fit`` call) spent 0.6-1.7 s reading them (the page
cache decides). The index holds their projections on ``DIMS`` axes (18 MB over 1,003 meshes);
``SearchIndex.preselect`` keeps the rows nearest to the query there, and only those are read in
full (``SearchIndex.rows``) for the exact ranking that follows.

**Contents** (``np.savez``, no pickle): ``key`` (the feature key's sha256, ``feature_key_hash``),
``mean`` (D,) and ``axes`` (D, DIMS) float64 (``fit_pca`` of every ``FIT_STRIDE``-th row of
each mesh, sparser beyond ``FIT_ROWS`` rows),
``proj`` (N, DIMS) float32 = (row - mean) @ axes of every row, ``counts`` (M,) int64: rows of
each mesh of the key that has features, in key order (``MESH_ORDER``), ``meshes`` (M,) their
sha256, ``skipped``: JSON of [(sha256, why)] of the accepted meshes left out (no or unreadable
features).

**Freshness.** The feature key is the list of (accepted mesh, its ``features.npy`` object or
None) in ``MESH_ORDER``; the index is fresh iff its ``key`` is the hash of the catalogue's key
now. A stale, missing or unreadable index is not used: retrieval then reads every row, as
without one. ``ucad-index build`` writes it at the end of each run, in a process of its own
(``main``; atomically: temporary file, fsync, rename), so deleting it loses nothing; ``gc`` and
``verify`` do not look at it.

No OpenCL here.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import resource
import sqlite3
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._db import (INDEX_UNREADABLE, SEARCH_INDEX, TMP_PREFIX, CatalogError, check_catalog_db,
                  feature_key, feature_key_hash, feature_objects, locate_db, npy_header,
                  open_search_index, search_index_key, will_need)

if TYPE_CHECKING:
    from .reader import MeshInfo

DIMS = 64          # principal axes kept (the fit's top 20 meshes were identical to the exact
#                    preselection's for 160 of 160 photos at 64 and at 128 axes: docs/FIT.md)
FIT_STRIDE = 4     # every 4th row (or sparser) of each mesh fits the axes ...
FIT_ROWS = 16384   # ... at most about this many in all (memory: FIT_ROWS x D x 4 bytes)
INDEX_CHUNK = 1024  # rows per float64 block of the index's covariance (~15 MB a block)
IOV_RUN = 1024          # rows one preadv reads at most (Linux's IOV_MAX)
PREFETCH_MESHES = 256   # objects whose rows are asked for together (_advise) before reading


def fit_pca(x: np.ndarray, dims: int, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and top-``dims`` principal axes (D, dims), float64, of the rows of ``x``
    (summed in float64 blocks of ``chunk`` rows).

    Axes are eigenvectors of the covariance, largest eigenvalue first; each axis's sign makes
    its largest-magnitude entry positive (first such entry on ties), so the fit is deterministic.
    """
    n = x.shape[0]
    mean = sum(x[i:i + chunk].astype(np.float64).sum(0) for i in range(0, n, chunk)) / n
    cov = np.zeros((x.shape[1], x.shape[1]))
    for i in range(0, n, chunk):
        c = x[i:i + chunk].astype(np.float64) - mean
        cov += c.T @ c
    cov /= n
    vals, vecs = np.linalg.eigh(cov)
    order = np.argsort(-vals, kind="stable")[:dims]
    axes = vecs[:, order]
    pivot = np.argmax(np.abs(axes), axis=0)
    axes *= np.where(axes[pivot, np.arange(dims)] < 0, -1.0, 1.0)
    return mean, np.ascontiguousarray(axes)


def one_blas_thread():
    """A context in which NumPy's BLAS and LAPACK run on one thread (``threadpoolctl``): with
    more, OpenBLAS splits a product's sums differently (``c.T @ c`` of 1,024 rows gave other bits
    on 1 and 2 threads), and the index must be the same bytes whatever the thread count. Another
    CPU's BLAS kernels may still round differently (a Zen 4 and a Xeon did: docs/OPENCL.md)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1, user_api="blas")


def write_search_index(root: Path, key, dims: int = DIMS, durable: bool = True) -> str:
    """Write ``root/SEARCH_INDEX`` for the feature key ``key`` (``_db.feature_key`` of the
    catalogue now: the writer's, under its lock) unless the one there is fresh for it; a line
    saying what was done. Each ``features.npy`` is read twice, one mesh at a time (every
    ``FIT_STRIDE``-th row of each, or sparser so that about ``FIT_ROWS`` rows in all, fits the
    axes; then every row is projected), so memory stays at the projections and the fitting
    rows (~0.3 GB over 1,003 meshes: the build runs this in a process of its own, ``main``,
    so that its driver stays small). Meshes without readable (V, D) float features are left
    out (``skipped``); with no rows at all the old index is removed."""
    root = Path(root)
    path = root / SEARCH_INDEX
    try:
        if search_index_key(root) == feature_key_hash(key):
            return "search index: fresh"
    except INDEX_UNREADABLE:
        pass                                       # unreadable: written anew
    readable, skipped = feature_objects(root, key)
    items: list[tuple[str, Path, tuple[int, ...]]] = []
    for sha, p, shape, _ in readable:
        if len(shape) != 2 or (items and shape[1] != items[0][2][1]) or not shape[0]:
            skipped.append((sha, f"features.npy has shape {shape}"))
        else:
            items.append((sha, p, shape))
    order = {sha: i for i, (sha, _) in enumerate(key)}        # the key's order, as before
    skipped.sort(key=lambda s: order[s[0]])
    for old in root.glob(f"{TMP_PREFIX}{SEARCH_INDEX}.*"):    # a killed writer's (one writer
        old.unlink(missing_ok=True)                           # at a time)
    if not items:
        path.unlink(missing_ok=True)
        return "search index: no features to index"
    stride = max(FIT_STRIDE, -(-sum(shape[0] for _, _, shape in items) // FIT_ROWS))
    with one_blas_thread():
        fit = np.concatenate([np.load(p, allow_pickle=False)[::stride].astype(np.float32)
                              for _, p, _ in items])
        dims = min(dims, fit.shape[1], len(fit))
        mean, axes = fit_pca(fit, dims, INDEX_CHUNK)
        del fit
        counts = np.array([shape[0] for _, _, shape in items], np.int64)
        proj = np.empty((int(counts.sum()), dims), np.float32)
        at = 0
        for (_, p, _), n in zip(items, counts):
            proj[at:at + n] = (np.load(p, allow_pickle=False).astype(np.float64) - mean) @ axes
            at += n
    tmp = path.with_name(f"{TMP_PREFIX}{SEARCH_INDEX}.{os.getpid()}.{uuid.uuid4().hex[:8]}")
    try:
        with open(tmp, "wb") as f:
            np.savez(f, key=np.array(feature_key_hash(key)), mean=mean, axes=axes, proj=proj,
                     counts=counts, meshes=np.array([sha for sha, _, _ in items], "U64"),
                     skipped=np.array(json.dumps([list(x) for x in skipped])))
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return (f"search index: {len(proj)} rows of {len(items)} meshes on {dims} axes "
            f"({path.stat().st_size / 2**20:.1f} MB)")


@dataclass
class SearchIndex:
    """A fresh search index (``CatalogReader.search_index()``): ``meshes`` (the accepted meshes
    with features, ``feature_table`` order), ``mesh``/``view`` (N,) of every row as in
    ``FeatureTable``, ``proj`` (N, d) float32, ``mean`` (D,), ``axes`` (D, d), ``skipped`` as in
    ``FeatureTable``; ``paths``: each mesh's ``features.npy`` object. Arrays are read-only."""

    meshes: list["MeshInfo"]
    mesh: np.ndarray
    view: np.ndarray
    proj: np.ndarray
    mean: np.ndarray
    axes: np.ndarray
    paths: list[Path]
    skipped: tuple[tuple[str, str], ...] = ()
    sq_norms: np.ndarray = field(init=False, repr=False)              # |proj|^2 per row
    _start: dict[int, int] = field(default_factory=dict, repr=False)   # data offset per mesh
    _headers: dict[int, bytes] = field(default_factory=dict, repr=False)   # rows -> npy header

    def __post_init__(self) -> None:
        self.sq_norms = np.einsum("ij,ij->i", self.proj, self.proj)

    def preselect(self, query: np.ndarray, n: int) -> np.ndarray:
        """Ascending row numbers of the ``n`` rows nearest to ``query`` (D,), made unit, by
        squared distance of the projections (float32, expanded as |x|^2 - 2 x.p + |p|^2; ties:
        the lower row)."""
        q = np.asarray(query, np.float64)
        q = q / max(float(np.linalg.norm(q)), 1e-30)
        p = ((q - self.mean) @ self.axes).astype(np.float32)
        d = self.sq_norms - 2.0 * (self.proj @ p) + p @ p     # float32, |x|^2 - 2 x.p + |p|^2
        if n >= len(d):
            return np.arange(len(d), dtype=np.int64)
        keep = np.argpartition(d, n - 1)[:n]
        cut = d[keep].max()                         # ties at the cut: the lower rows
        below, at = np.flatnonzero(d < cut), np.flatnonzero(d == cut)
        return np.sort(np.concatenate([below, at[:n - len(below)]]))

    def rows(self, rows: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(len(rows), D) float32 full rows, read from the meshes' ``features.npy`` objects
        into ``out`` (C-contiguous; None: a new array) and returned (CatalogError when one is
        gone or no longer what the index says). The objects are
        taken ``PREFETCH_MESHES`` at a time: every row of a batch is asked of the kernel
        first (``_open_advised``), then read, so that on a cold page cache the batch's disk
        reads are waited for together rather than one after another."""
        rows = np.asarray(rows, np.int64)
        shape = (len(rows), self.mean.shape[0])
        if out is None:
            out = np.empty(shape, np.float32)
        elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}")
        if not len(rows):
            return out
        order = np.argsort(self.mesh[rows], kind="stable")
        meshes = self.mesh[rows][order]
        cuts = np.flatnonzero(np.diff(meshes)) + 1
        ks = meshes[np.r_[0, cuts]]                   # each group's mesh
        counts = np.searchsorted(self.mesh, ks, "right") - np.searchsorted(self.mesh, ks)
        groups = [(int(k), int(n), self.view[rows[sel]].tolist(), sel)
                  for k, n, sel in zip(ks, counts, np.split(order, cuts))]
        for b in range(0, len(groups), PREFETCH_MESHES):
            batch = groups[b:b + PREFETCH_MESHES]
            fds: dict[int, int] = {}
            try:
                for k, n, views, _ in batch:
                    fds[k] = self._open_advised(k, n, views)
                for k, n, views, sel in batch:
                    self._read(k, n, views, out, sel, fds[k])
            finally:
                for fd in fds.values():
                    os.close(fd)
        return out

    def _open_advised(self, k: int, n: int, views: list[int]) -> int:
        """Mesh ``k``'s object (``n`` rows) opened, the kernel asked to start reading its rows
        ``views`` (and its header, until its data offset is known) into the page cache
        (``_db.will_need``; consecutive views one request)."""
        D = self.mean.shape[0]
        try:
            fd = os.open(self.paths[k], os.O_RDONLY)
        except OSError as exc:
            raise CatalogError(f"mesh {self.meshes[k].sha256[:12]}: features.npy cannot be "
                               f"read as the search index says ({exc})") from None
        start = self._start.get(k)
        if start is None:
            start = len(self._header(n, D))         # the build's (np.save's) layout
            will_need(fd, 0, start)
        if start >= 0:
            first = last = -2
            for v in views + [-2]:                    # runs of consecutive views
                if v == last + 1:
                    last = v
                    continue
                if first >= 0:
                    will_need(fd, start + first * D * 4, (last + 1 - first) * D * 4)
                first = last = v
        return fd

    def _read(self, k: int, n: int, views: list[int], out: np.ndarray, at: np.ndarray,
              fd: int) -> None:
        """Rows ``views`` of mesh ``k`` (``n`` rows, its object open as ``fd``) into
        ``out[at]``: read in place when the object holds raw float32 rows (its data offset
        found once per index; one preadv per run of consecutive views, at most ``IOV_RUN``),
        else through np.load."""
        path = self.paths[k]
        D = self.mean.shape[0]
        try:
            if k not in self._start:
                self._start[k] = self._data_start(fd, path, n, D)
            start = self._start[k]
            if start < 0:
                out[at] = np.load(path, allow_pickle=False)[views]
                return
            at_list, r = at.tolist(), 0
            while r < len(views):                     # a run of consecutive views: one preadv
                e = r + 1
                while e < len(views) and views[e] == views[e - 1] + 1 and e - r < IOV_RUN:
                    e += 1
                bufs = [out[i].data.cast("B") for i in at_list[r:e]]
                if os.preadv(fd, bufs, start + views[r] * D * 4) != (e - r) * D * 4:
                    raise EOFError("short read")
                r = e
        except (OSError, ValueError, EOFError) as exc:
            raise CatalogError(f"mesh {self.meshes[k].sha256[:12]}: features.npy cannot be "
                               f"read as the search index says ({exc})") from None

    def _header(self, n: int, D: int) -> bytes:
        """``npy_header_bytes((n, D))``, kept per row count."""
        head = self._headers.get(n)
        if head is None:
            head = self._headers[n] = npy_header_bytes((n, D))
        return head

    def _data_start(self, fd: int, path: Path, n: int, D: int) -> int:
        """Where the (n, D) raw float32 rows start in the open object ``fd``, -1 when they are
        not stored raw (then np.load reads it). An object that starts with ``np.save``'s own
        header for that shape and is exactly that long (the build's) is taken without parsing
        the header (one small read: ~1,000 objects a photo); any other is parsed
        (``npy_header``); ValueError when its shape is not what the index says."""
        head = self._header(n, D)
        if (os.pread(fd, len(head), 0) == head
                and os.fstat(fd).st_size == len(head) + n * D * 4):
            return len(head)
        shape, raw = npy_header(path)
        if shape != (n, D):
            raise ValueError(f"shape {shape}, the index says {(n, D)}")
        return os.fstat(fd).st_size - n * D * 4 if raw else -1


def npy_header_bytes(shape: tuple[int, ...]) -> bytes:
    """The header ``np.save`` writes for a C-order little-endian float32 array of ``shape``
    (format 1.0), the one the build's ``features.npy`` objects start with."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": "<f4", "fortran_order": False, "shape": tuple(int(x) for x in shape)})
    return buf.getvalue()


def load_search_index(root: Path, key, metas: list["MeshInfo"],
                      objects: dict[str, Path]) -> tuple[SearchIndex | None, str]:
    """(the index at ``root``, '') when it is fresh for ``key`` (the catalogue's feature key
    now), else (None, why). ``metas``: the accepted meshes (``MESH_ORDER``); ``objects``: sha256
    -> path of its features object."""
    try:
        z = open_search_index(root)
        if z is None:
            return None, "no search index (built before it existed: the next build writes it)"
        with z:
            if str(z["key"]) != feature_key_hash(key):
                return None, "the search index is stale (meshes changed since it was written)"
            mean, axes, proj = z["mean"], z["axes"], z["proj"]
            counts, shas = z["counts"], [str(s) for s in z["meshes"]]
            skipped = tuple(tuple(s) for s in json.loads(str(z["skipped"])))
    except INDEX_UNREADABLE as exc:
        return None, f"the search index cannot be read ({exc})"
    by_sha = {m.sha256: m for m in metas}
    ok = (mean.ndim == 1 and axes.shape[:1] == mean.shape and proj.ndim == 2
          and proj.shape[1] == axes.shape[1] and counts.shape == (len(shas),)
          and int(counts.sum()) == len(proj) and all(s in by_sha and s in objects for s in shas))
    if not ok:
        return None, "the search index is inconsistent with the catalogue"
    idx = SearchIndex(
        meshes=[by_sha[s] for s in shas],
        mesh=np.repeat(np.arange(len(shas), dtype=np.int64), counts),
        view=np.concatenate([np.arange(n, dtype=np.int64) for n in counts]),
        proj=proj, mean=mean, axes=axes, paths=[objects[s] for s in shas],
        skipped=skipped)   # type: ignore[arg-type]
    for a in (idx.mesh, idx.view, idx.proj, idx.mean, idx.axes, idx.sq_norms):
        a.flags.writeable = False
    return idx, ""


def main(argv: list[str] | None = None) -> int:
    """``main([ROOT, "--no-fsync"?])``: bring ROOT's search index up to date and print what was
    done; 1 with one line on an error. The build runs it in a process of its own while it holds
    the writer lock (``ucad_cl.build``); run alone, it must not race a build."""
    ap = argparse.ArgumentParser(prog="ucad_catalog.searchindex",
                                 description=main.__doc__.splitlines()[0] if main.__doc__ else "")
    ap.add_argument("root", type=Path)
    ap.add_argument("--no-fsync", action="store_true", help="skip the fsync (a non-durable build)")
    args = ap.parse_args(argv)
    try:
        root, db = locate_db(args.root)
        conn = sqlite3.connect(f"{db.resolve().as_uri()}?mode=ro", uri=True, timeout=30.0)
        try:
            check_catalog_db(conn, db)
            key = feature_key(conn)
        finally:
            conn.close()
        line = write_search_index(root, key, durable=not args.no_fsync)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"{line}; peak {peak:.0f} MB")
    except (CatalogError, OSError, ValueError, EOFError, sqlite3.Error, MemoryError) as exc:
        print(f"search index not written: {type(exc).__name__}: {exc}")
        return 1
    return 0


__all__ = ["DIMS", "SearchIndex", "fit_pca", "load_search_index", "main", "one_blas_thread",
           "write_search_index"]

