"""The catalogue as a product: the reader installed alone (no OpenCL, no trimesh) reading a
catalogue the full package built, mesh ids and path spellings, views by angle, the one-part EXR
decoder against OpenEXR, and the command-line cases of issue 14.

References are independent of the code under test: views re-rendered by the pipeline, edges
recomputed from them, raw sqlite3 rows, OpenEXR's own decoder, brute-force loops.
"""
from __future__ import annotations

import json
import os
import sqlite3
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ucad_catalog import CatalogError, CatalogReader
from ucad_catalog.exr import ViewStackFile

ROOT = Path(__file__).resolve().parents[1]
CATALOG_PY = ROOT / ".venv-catalog" / "bin" / "python"


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A small library (3 vehicles, a one-material mesh, a broken file) and its catalogue."""
    pytest.importorskip("pyopencl")
    import trimesh

    from ucad_cl.build import BuildOptions, build
    from ucad_cl.synth import make_vehicle, write_library

    base = tmp_path_factory.mktemp("reader")
    lib = base / "lib"
    write_library(lib, 3, seed=21, messy_fraction=0.0, progress=False)
    mesh = make_vehicle(7, "sedan").mesh()
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(lib / "single.glb")
    (lib / "broken.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    opts = BuildOptions(azimuth_step=45.0, elevations=(0.0, 30.0), size=64)
    build(lib, base / "cat", opts, progress=False, log=lambda *a: None)
    return lib, base / "cat", opts


def references(lib: Path, cat: Path, opts) -> dict:
    """Per accepted mesh: its views re-rendered and its edges recomputed by the pipeline."""
    from ucad_cl.cameras import make_ring
    from ucad_cl.edges import material_edges
    from ucad_cl.ingest import load_mesh
    from ucad_cl.render import render_views

    ring = make_ring(azimuth_step=opts.azimuth_step, elevations=opts.elevations, size=opts.size)
    out = {}
    con = sqlite3.connect(cat / "catalog.sqlite")
    for sha, path in con.execute("SELECT sha256, path FROM meshes WHERE state='accepted'"):
        mesh = load_mesh(lib / path)                              # oriented, as the build does
        views = render_views(mesh, ring)
        label_ring = views.select(slice(0, len(ring.azimuth) // len(opts.elevations)))
        out[sha] = {"views": views, "edges": material_edges(label_ring).edges > 0, "ring": ring,
                    "orientation": mesh.orientation.as_dict(),
                    "table": con.execute("SELECT idx, part FROM materials m JOIN meshes x ON "
                                         "m.mesh_id=x.id WHERE x.sha256=?", (sha,)).fetchall()}
    con.close()
    return out


STANDALONE = r"""
import importlib.util, json, sys
import numpy as np
for name in ("pyopencl", "trimesh", "ucad_cl", "cv2"):
    assert importlib.util.find_spec(name) is None, f"{name} is installed in the reader's venv"
import ucad_catalog
cat = ucad_catalog.open(sys.argv[1])
out, arrays = {}, {}
for m in cat.meshes():
    views = cat.views(m.id[:8])                                 # an 8-digit prefix names it
    rec = {"n_views": len(views), "angles": [(v.index, v.azimuth, v.elevation) for v in views],
           "view_angles": [(a.index, a.azimuth, a.elevation) for a in cat.view_angles(m.id)],
           "K": views[0].K.tolist(), "w2c": [v.w2c.tolist() for v in views],
           "parts": [(p.index, p.name, p.part, p.props) for p in cat.parts(m.id)],
           "by_angle": [cat.nearest_view(m.id, a, e) for a, e in
                        ((100.0, 25.0), (350.0, 0.0), (181.0, 14.9), (0.0, 89.0))]}
    v = cat.view(m.id, azimuth=100.0, elevation=25.0)
    rec["view_by_angle"] = v.view
    for i in range(len(views)):
        r = cat.view(m.id, i)
        arrays[f"{m.id}/mat/{i}"], arrays[f"{m.id}/tri/{i}"] = r.mat_id, r.tri_id
        arrays[f"{m.id}/depth/{i}"] = r.depth
        assert np.array_equal(cat.material_map(m.id, i), r.mat_id)
        assert np.array_equal(cat.depth(m.id, i), r.depth, equal_nan=True)
        assert np.array_equal(cat.triangle_map(m.id, i), r.tri_id)
        bare = cat.view(m.id, i, part_masks=False)     # the maps and cameras alone
        assert bare.part_masks == {} and r.part_masks and bare.stats == r.stats
        assert all(np.array_equal(getattr(bare, k), getattr(r, k), equal_nan=True)
                   for k in ("mat_id", "tri_id", "depth", "K", "w2c"))
        for part, mask in cat.part_masks(m.id, i).items():
            arrays[f"{m.id}/mask/{part}/{i}"] = mask
        if i < len(cat.edges(m.id)):                       # the label ring's views
            arrays[f"{m.id}/edges/{i}"] = cat.edges(m.id, i)
        else:
            try:
                cat.edges(m.id, i)
                raise AssertionError(f"edges of view {i} outside the label ring")
            except ucad_catalog.CatalogError as exc:
                assert "label ring" in str(exc), exc
    arrays[f"{m.id}/features"] = cat.features(m.id)
    assert np.array_equal(cat.edges(m.id), np.stack([arrays[f"{m.id}/edges/{i}"]
                                                     for i in range(len(cat.edges(m.id)))]))
    rec["record_keys"] = sorted(cat.record(m.id))
    e = cat.entry(m.name)
    assert (e.id, e.info.path, [p.part for p in e.parts], len(e.views)) == \
        (m.id, m.path, [p.part for p in cat.parts(m.id)], len(views))
    assert all(p.is_file() for p in e.artifacts.values())
    rec["orientation"] = e.orientation
    rec["provenance"] = {k: v for k, v in e.provenance.items() if k != "run_started"}
    rec["artifact_kinds"] = sorted(cat.record(m.id)["artifacts"])
    out[m.id] = rec
table = cat.feature_table()
assert cat.feature_table() is table and table.skipped == ()
assert [m.id for m in table.meshes] == [m.id for m in cat.meshes()]
assert np.array_equal(table.feats, np.concatenate([arrays[f"{m.id}/features"]
                                                   for m in cat.meshes()]))
out["_rejected"] = [(m.path, m.reason) for m in cat.meshes("rejected")]
cat.export(sys.argv[2] + "/cat.jsonl")
cat.export(sys.argv[2] + "/cat.parquet")
bad = [k for k in sys.modules if k.split(".")[0] in ("pyopencl", "trimesh", "ucad_cl", "cv2")]
assert not bad, bad
np.savez(sys.argv[2] + "/arrays.npz", **arrays)
json.dump(out, open(sys.argv[2] + "/out.json", "w"))
print("ok")
"""


def test_reader_installed_alone_reads_every_artifact(built, tmp_path):
    """In .venv-catalog (only ucad_catalog, numpy, OpenEXR, pyarrow): every artifact kind, views
    by angle, part masks and edges equal what the pipeline renders and computes."""
    if not CATALOG_PY.exists():
        if os.environ.get("UCAD_REQUIRE_CATALOG_VENV"):
            pytest.fail(f"{CATALOG_PY} missing: scripts/catalog-venv.sh should have made it")
        pytest.skip("no .venv-catalog (bash scripts/catalog-venv.sh makes it)")
    lib, cat, opts = built
    run = subprocess.run([str(CATALOG_PY), "-I", "-c", STANDALONE, str(cat), str(tmp_path)],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert run.stdout.strip() == "ok", run.stderr[-3000:]
    out = json.loads((tmp_path / "out.json").read_text())
    arrays = np.load(tmp_path / "arrays.npz")
    refs = references(lib, cat, opts)
    assert sorted(k for k in out if k != "_rejected") == sorted(refs)
    assert sorted(r for _, r in out["_rejected"]) == ["too_few_materials", "unreadable"]
    for sha, ref in refs.items():
        rec, views, ring = out[sha], ref["views"], ref["ring"]
        assert rec["n_views"] == ring.n_views == 16
        assert [tuple(a) for a in rec["angles"]] == \
            [(v, ring.azimuth[v], ring.elevation[v]) for v in range(ring.n_views)]
        assert rec["view_angles"] == rec["angles"]
        assert np.array_equal(rec["K"], ring.K) and np.array_equal(rec["w2c"], ring.w2c)
        assert rec["orientation"] == json.loads(json.dumps(ref["orientation"]))   # the stage's record
        assert rec["orientation"]["source"] == "auto" and len(rec["orientation"]["rotation"]) == 3
        assert rec["by_angle"] == [brute_nearest(ring, a, e) for a, e in
                                   ((100.0, 25.0), (350.0, 0.0), (181.0, 14.9), (0.0, 89.0))]
        assert rec["by_angle"][1] == 0 and rec["view_by_angle"] == rec["by_angle"][0]
        assert rec["artifact_kinds"] == ["edges.npy.gz", "features.npy", "parts.png",
                                         "views.exr"]
        prov = rec["provenance"]
        assert (prov["library_root"], prov["run_id"], prov["engine"]) == (str(lib), 1, "local")
        assert prov["options"]["size"] == opts.size and prov["options"]["code"]
        lut = dict(ref["table"])
        for v in range(ring.n_views):
            assert np.array_equal(arrays[f"{sha}/mat/{v}"], views.mat_id[v])
            assert np.array_equal(arrays[f"{sha}/tri/{v}"], views.tri_id[v])
            assert np.array_equal(arrays[f"{sha}/depth/{v}"], views.depth[v])
            if v < len(ref["edges"]):                   # the label ring (0 deg) has edges
                assert np.array_equal(arrays[f"{sha}/edges/{v}"], ref["edges"][v])
            else:
                assert f"{sha}/edges/{v}" not in arrays
            for part in set(lut.values()):
                want = np.isin(views.mat_id[v], [i + 1 for i, p in lut.items() if p == part])
                assert np.array_equal(arrays[f"{sha}/mask/{part}/{v}"], want), (part, v)
        with sqlite3.connect(cat / "catalog.sqlite") as con:
            obj = con.execute("SELECT a.sha256 FROM artifacts a JOIN meshes m ON a.mesh_id=m.id "
                              "WHERE m.sha256=? AND kind='features.npy'", (sha,)).fetchone()[0]
        assert np.array_equal(arrays[f"{sha}/features"],
                              np.load(cat / "objects" / obj[:2] / obj))
    pq = pytest.importorskip("pyarrow.parquet")
    assert pq.read_table(tmp_path / "cat.parquet").num_rows == 5
    assert len((tmp_path / "cat.jsonl").read_text().splitlines()) == 5


def test_feature_table_stacks_every_accepted_mesh_once(built, tmp_path):
    """``feature_table``: the features objects (raw sqlite3 rows, np.load) stacked in the
    listing's order with each row's mesh and view; the same object while nothing changed; a
    mesh whose object is gone is left out with its reason, the others' rows unchanged."""
    import shutil

    _, cat, _ = built
    with sqlite3.connect(cat / "catalog.sqlite") as con:
        obj = dict(con.execute("SELECT m.sha256, a.sha256 FROM artifacts a JOIN meshes m ON "
                               "a.mesh_id=m.id WHERE m.state='accepted' AND "
                               "a.kind='features.npy'").fetchall())
    with CatalogReader(cat) as r:
        order = [m.sha256 for m in r.meshes()]
        t = r.feature_table()
        assert r.feature_table() is t and t.skipped == ()
    assert len(order) == 3 and [m.sha256 for m in t.meshes] == order
    want = [np.load(cat / "objects" / obj[s][:2] / obj[s]) for s in order]
    assert t.feats.dtype == np.float32 and np.array_equal(t.feats, np.concatenate(want))
    assert not t.feats.flags.writeable                   # shared by every caller of the reader
    assert t.mesh.tolist() == [k for k, w in enumerate(want) for _ in range(len(w))]
    assert t.view.tolist() == [v for w in want for v in range(len(w))]
    assert all(np.array_equal(t.rows_of(k), w) for k, w in enumerate(want))

    def obj_path(root, sha):
        return root / "objects" / obj[sha][:2] / obj[sha]

    copy = tmp_path / "cat"                   # one object gone, one in another layout
    shutil.copytree(cat, copy)
    gone = order[1]
    obj_path(copy, gone).unlink()
    with open(obj_path(copy, order[0]), "wb") as f:          # float64, Fortran order: np.load
        np.save(f, np.asfortranarray(want[0].astype(np.float64)))
    with CatalogReader(copy) as r:
        t2 = r.feature_table()
    assert [m.sha256 for m in t2.meshes] == [order[0], order[2]]
    assert len(t2.skipped) == 1 and t2.skipped[0][0] == gone
    assert "features.npy unreadable" in t2.skipped[0][1]
    assert np.array_equal(t2.feats, np.concatenate([want[0], want[2]]))
    assert t2.mesh.tolist() == [k for k, w in enumerate([want[0], want[2]])
                                for _ in range(len(w))]

    short = tmp_path / "short"                # truncated, or not numbers: left out, not misread
    shutil.copytree(cat, short)
    data = obj_path(short, order[2]).read_bytes()
    obj_path(short, order[2]).write_bytes(data[:-100])
    with open(obj_path(short, order[0]), "wb") as f:         # strings of the right shape
        np.save(f, np.full(want[0].shape, "x"))
    with CatalogReader(short) as r:
        t3 = r.feature_table()
    assert [m.sha256 for m in t3.meshes] == [order[1]]
    assert dict(t3.skipped).keys() == {order[0], order[2]}
    assert "not a real number type" in dict(t3.skipped)[order[0]]
    assert "bytes of data" in dict(t3.skipped)[order[2]]
    assert np.array_equal(t3.feats, want[1])


def test_search_index_projects_every_row_and_goes_stale(built, tmp_path, capsys):
    """The build's ``search_index.npz``: the projections are (row - mean) @ axes of every stored
    row, the axes an orthonormal basis of the fitting rows' top principal subspace (their
    variances = NumPy's largest covariance eigenvalues), ``preselect`` the nearest projections
    (brute force, ties to the lower row), ``rows`` the stored rows; a catalogue whose meshes
    changed has a stale index (not used) until its writer refreshes it (removing a killed
    writer's temporary file); a damaged file or a zip bomb is not used; an object damaged after
    indexing is an error naming the mesh."""
    import shutil

    from ucad_catalog import searchindex
    from ucad_catalog.searchindex import FIT_STRIDE

    _, cat, _ = built
    assert (cat / "search_index.npz").is_file()
    with CatalogReader(cat) as r:
        t = r.feature_table()
        idx, why = r.search_index()
        assert why == "" and r.search_index()[0] is idx and r.status()["search_index"] == "fresh"
    assert [m.sha256 for m in idx.meshes] == [m.sha256 for m in t.meshes]
    assert np.array_equal(idx.mesh, t.mesh) and np.array_equal(idx.view, t.view)
    X = t.feats.astype(np.float64)
    fit_rows = np.concatenate([t.rows_of(k)[::FIT_STRIDE] for k in range(len(t.meshes))])
    d = idx.axes.shape[1]
    assert d == min(64, len(fit_rows)) and np.allclose(idx.mean, fit_rows.mean(0), atol=1e-7)
    assert np.allclose(idx.axes.T @ idx.axes, np.eye(d), atol=1e-9)
    cov = np.cov(fit_rows.astype(np.float64), rowvar=False, bias=True)
    top = np.sort(np.linalg.eigvalsh(cov))[::-1][:d]
    assert np.allclose(np.diag(idx.axes.T @ cov @ idx.axes), top, rtol=1e-6, atol=1e-12)
    assert np.allclose(idx.proj, (X - idx.mean) @ idx.axes, atol=1e-5)
    q = X[7] + np.random.default_rng(0).normal(0, 0.02, X.shape[1])
    p = ((q / np.linalg.norm(q) - idx.mean) @ idx.axes).astype(np.float32)
    dist = ((idx.proj - p) ** 2).sum(1)
    want = sorted(sorted(range(len(dist)), key=lambda i: (dist[i], i))[:10])
    assert idx.preselect(q, 10).tolist() == want and 7 in want
    assert idx.preselect(q, 10 ** 6).tolist() == list(range(len(X)))
    rows = np.array([len(X) - 1, 0, 20, 19])
    assert np.array_equal(idx.rows(rows), t.feats[rows])
    assert np.array_equal(idx.rows(np.arange(32, 48)), t.rows_of(2))
    assert np.array_equal(t.rows(rows), t.feats[rows])
    out = np.full((6, X.shape[1]), np.nan, np.float32)          # into a caller's array
    assert idx.rows(rows, out=out[1:5]) is not None and np.array_equal(out[1:5], t.feats[rows])
    assert np.isnan(out[[0, 5]]).all()
    for bad in (np.empty((3, X.shape[1]), np.float32), np.empty((4, X.shape[1])),
                np.empty((X.shape[1], 4), np.float32).T):
        with pytest.raises(ValueError, match="C-contiguous float32"):
            idx.rows(rows, out=bad)

    copy = tmp_path / "cat"                  # a mesh gone: stale until the writer refreshes
    shutil.copytree(cat, copy)
    with sqlite3.connect(copy / "catalog.sqlite") as con:
        con.execute("PRAGMA foreign_keys=ON")
        con.execute("DELETE FROM meshes WHERE sha256=?", (t.meshes[0].sha256,))
    with CatalogReader(copy) as r:
        assert r.search_index() == (None, "the search index is stale (meshes changed since "
                                          "it was written)")
        assert r.status()["search_index"] == "stale"
    killed = copy / ".tmp-search_index.npz.99999.deadbeef"      # a killed writer's file
    killed.write_bytes(b"partial")
    assert searchindex.main([str(copy)]) == 0                 # what the build runs
    assert capsys.readouterr().out.startswith(f"search index: {len(X) - 16} rows of 2 ")
    assert not killed.exists()
    assert searchindex.main([str(copy), "--no-fsync"]) == 0
    assert capsys.readouterr().out.startswith("search index: fresh; peak ")
    with CatalogReader(copy) as r:
        idx2, _ = r.search_index()
    assert [m.sha256 for m in idx2.meshes] == [m.sha256 for m in t.meshes[1:]]
    assert np.array_equal(idx2.rows(np.arange(len(idx2.mesh))), t.feats[16:])

    (copy / "search_index.npz").write_bytes(b"PK\x03\x04 not a zip")
    with CatalogReader(copy) as r:
        index, why = r.search_index()
        assert r.status()["search_index"] == "unreadable"
    assert index is None and why.startswith("the search index cannot be read")

    import zipfile                           # a compressed member far larger than the file
    with zipfile.ZipFile(copy / "search_index.npz", "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("proj.npy", b"\0" * 10 ** 7)
    with CatalogReader(copy) as r:
        index, why = r.search_index()
        assert r.status()["search_index"] == "unreadable"
    assert index is None and "more than the file's" in why
    (copy / "search_index.npz").unlink()
    with CatalogReader(copy) as r:
        assert r.status()["search_index"] == "none" and r.search_index()[0] is None

    shutil.copy(cat / "search_index.npz", copy / "search_index.npz")   # fresh for `cat` only
    damaged = idx.paths[1]
    back = damaged.read_bytes()
    try:
        damaged.write_bytes(back[:len(back) // 2])          # its last rows gone
        with pytest.raises(CatalogError, match=f"mesh {idx.meshes[1].sha256[:12]}: features"):
            idx.rows(np.array([16, 31]))
        damaged.unlink()
        with pytest.raises(CatalogError, match=f"mesh {idx.meshes[1].sha256[:12]}: features"):
            idx.rows(np.arange(16, 32))
    finally:
        damaged.write_bytes(back)


def test_search_index_is_the_same_bytes_whatever_the_blas_thread_count(built, tmp_path):
    """The index written with NumPy's BLAS allowed 1 and 4 threads (``OPENBLAS_NUM_THREADS``,
    each in a fresh process): the same mean, axes and projections, bit for bit (OpenBLAS sums
    a product differently per thread count; the writer runs it on one: ``one_blas_thread``)."""
    import shutil

    _, cat, _ = built
    got = []
    for threads in ("1", "4"):
        copy = tmp_path / f"cat{threads}"
        shutil.copytree(cat, copy)
        (copy / "search_index.npz").unlink()
        env = {**os.environ, "OPENBLAS_NUM_THREADS": threads, "OMP_NUM_THREADS": threads}
        run = subprocess.run([sys.executable, "-c", "import sys; from ucad_catalog.searchindex "
                              "import main; sys.exit(main(sys.argv[1:]))", str(copy)],
                             env=env, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stdout + run.stderr
        with np.load(copy / "search_index.npz") as z:
            got.append({k: z[k].tobytes() for k in ("mean", "axes", "proj")})
    assert got[0] == got[1]


def test_search_index_reads_rows_whatever_wrote_the_object(built, tmp_path):
    """``SearchIndex.rows`` takes an object that starts with ``np.save``'s own header for the
    shape (``npy_header_bytes``: what the build writes) without parsing it, and reads any other
    ``.npy`` of the same rows the same (a 2.0 header, float64, Fortran order: parsed); an
    object of another shape is an error naming the mesh."""
    import io
    import shutil

    from ucad_catalog.searchindex import npy_header_bytes

    _, cat, _ = built
    buf = io.BytesIO()
    np.save(buf, np.zeros((5, 7), np.float32))
    assert buf.getvalue().startswith(npy_header_bytes((5, 7)))
    assert len(buf.getvalue()) == len(npy_header_bytes((5, 7))) + 5 * 7 * 4
    copy = tmp_path / "cat"
    shutil.copytree(cat, copy)
    with CatalogReader(copy) as r:
        t = r.feature_table()
        idx, _ = r.search_index()
        path = idx.paths[1]
        rows = t.rows_of(1)
        assert path.read_bytes().startswith(npy_header_bytes(rows.shape))
        assert np.array_equal(idx.rows(np.arange(16, 32)), rows)
    for other in (lambda f: np.lib.format.write_array(f, rows, version=(2, 0)),
                  lambda f: np.save(f, rows.astype(np.float64)),
                  lambda f: np.save(f, np.asfortranarray(rows)),
                  lambda f: np.save(f, rows[:8])):
        with open(path, "wb") as f:
            other(f)
        with CatalogReader(copy) as r:          # a new reader: the object read anew
            idx, _ = r.search_index()
            if len(np.load(path)) != len(rows):
                with pytest.raises(CatalogError, match=f"mesh {idx.meshes[1].sha256[:12]}: "
                                   r"features.npy cannot be read .*\(shape \(8, "):
                    idx.rows(np.array([17, 20]))
            else:
                assert np.array_equal(idx.rows(np.array([31, 17, 20])), rows[[15, 1, 4]])


def test_search_index_rows_in_prefetch_batches_leave_no_descriptor(built, tmp_path,
                                                                  monkeypatch):
    """``SearchIndex.rows`` asks the kernel for a batch of objects' rows before reading them
    (``PREFETCH_MESHES`` objects a batch): any batch size gives the stored rows in the order
    asked, also where ``posix_fadvise`` does not exist (macOS, Windows) and whatever the rows
    one read takes (``IOV_RUN``: runs of consecutive views); no file descriptor
    stays open, also when an object is gone mid-way (an error naming that mesh)."""
    import shutil

    from ucad_catalog import searchindex

    _, cat, _ = built
    copy = tmp_path / "cat"
    shutil.copytree(cat, copy)
    fds = lambda: len(os.listdir("/proc/self/fd"))
    with CatalogReader(copy) as r:
        t = r.feature_table()
        idx, _ = r.search_index()
        ask = np.array([len(t.feats) - 1, 0, 20, 19, 33, 3])
        for size in (1, 2, 256):
            monkeypatch.setattr(searchindex, "PREFETCH_MESHES", size)
            before = fds()
            assert np.array_equal(idx.rows(ask), t.feats[ask])
            assert fds() == before
        with monkeypatch.context() as mp:
            mp.delattr(os, "posix_fadvise")
            assert np.array_equal(idx.rows(ask[::-1]), t.feats[ask[::-1]])
        runs = np.array([5, 6, 7, 8, 9, 2, 3, 30, 31, 29])    # runs of consecutive views, each
        for run in (1, 2, 1024):                                # read by preadv calls of at
            monkeypatch.setattr(searchindex, "IOV_RUN", run)    # most IOV_RUN rows
            assert np.array_equal(idx.rows(runs), t.feats[runs])
        idx.paths[1].unlink()
        monkeypatch.setattr(searchindex, "PREFETCH_MESHES", 2)
        with CatalogReader(copy) as r2:
            idx2, _ = r2.search_index()
            before = fds()
            with pytest.raises(CatalogError, match=f"mesh {idx2.meshes[1].sha256[:12]}"):
                idx2.rows(ask)
            assert fds() == before


def brute_nearest(ring, az: float, el: float) -> int:
    """Smallest angle between unit viewing directions, ties to the lower index (loop)."""
    def unit(a, e):
        a, e = np.radians(a), np.radians(e)
        return np.array([np.cos(e) * np.cos(a), np.sin(e), -np.cos(e) * np.sin(a)])
    q = unit(az, el)
    best, best_d = -1, np.inf
    for v in range(ring.n_views):
        d = float(np.arccos(np.clip(unit(ring.azimuth[v], ring.elevation[v]) @ q, -1, 1)))
        if d < best_d - 1e-12:
            best, best_d = v, d
    return best


def test_every_module_imports_without_opencl_trimesh_or_opencv():
    code = """
import pkgutil, sys, importlib
for name in ("ucad_cl", "pyopencl", "trimesh", "cv2"):
    sys.modules[name] = None                     # any import of them now raises ImportError
import ucad_catalog
mods = sorted(m.name for m in pkgutil.iter_modules(ucad_catalog.__path__))
for m in mods:
    importlib.import_module("ucad_catalog." + m)
from ucad_catalog.views import ViewSet, CameraRing
import numpy as np
vs = ViewSet(CameraRing(np.eye(3), np.zeros((2, 4, 4)), 3, 2, np.zeros(2), np.zeros(2), 1, .1),
             np.zeros((2, 2, 3), np.uint32), np.array([[[0, 1, 1], [2, 0, 0]]] * 2, np.uint16),
             np.zeros((2, 2, 3), np.float32))
assert vs.material_counts().tolist() == [[3, 2, 1], [3, 2, 1]]     # NumPy path, no OpenCV
print(" ".join(mods))
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, timeout=60)
    assert run.returncode == 0, run.stderr
    assert set(run.stdout.split()) >= {"reader", "store", "exr", "export", "views", "parts",
                                       "entry"}


# ---------------------------------------------------------------------------- ids and paths
def test_mesh_ids_prefixes_and_path_spellings(built, monkeypatch):
    lib, cat, _ = built
    with CatalogReader(cat) as r:
        metas = r.meshes(None)
        assert [m.path for m in metas] == sorted(m.path for m in metas)     # listed by path
        assert all(m.library_root == str(lib) for m in metas)
        m = next(x for x in metas if x.state == "accepted")
        assert m.id == m.sha256 and m.source == lib / m.path
        for key in (m.sha256, m.sha256[:8].upper(), str(lib / m.path), m.path,
                    f"./{m.path}", str(lib / "sub" / ".." / m.path), m.name):
            assert r.mesh(key).sha256 == m.sha256, key
        monkeypatch.chdir(lib.parent)
        assert r.mesh(f"lib/{m.path}").sha256 == m.sha256            # relative to here
        monkeypatch.chdir(lib)
        assert r.mesh(m.path).sha256 == m.sha256
        with pytest.raises(CatalogError, match="no mesh matches"):
            r.mesh(m.sha256[:7])                                     # below the minimum
        with pytest.raises(CatalogError, match="no mesh matches"):
            r.mesh("nothing.glb")
        assert [x.sha256 for x in r.find(m.sha256[:8])] == [m.sha256]
        with r.snapshot():                                           # snapshots nest
            assert r.entry(m.sha256[:8]).info.sha256 == m.sha256
            assert r.export(lib.parent / "nested.jsonl") == len(metas)


def test_mesh_named_through_symlinks_and_after_its_file_moved(built, tmp_path, monkeypatch):
    """A path key matches a recorded path that names the same file once symlinks are resolved,
    on either side, and a recorded file that is gone by its recorded path; another file of the
    library, a link to another file, or a missing file elsewhere match nothing by path."""
    lib, cat, _ = built
    with CatalogReader(cat) as r:
        metas = [m for m in r.meshes(None) if m.state == "accepted"]
        m, other = metas[0], metas[1]
        tmp_path.joinpath("lib_link").symlink_to(lib, target_is_directory=True)
        tmp_path.joinpath("file_link.bin").symlink_to(m.source)
        tmp_path.joinpath("other_link.bin").symlink_to(other.source)
        for key in (tmp_path / "lib_link" / m.path, tmp_path / "file_link.bin"):
            assert [x.sha256 for x in r.find(str(key))] == [m.sha256], key
        assert [x.sha256 for x in r.find(str(tmp_path / "other_link.bin"))] == [other.sha256]
        assert r.find(str(tmp_path / "lib_link" / "missing.glb")) == []
        moved = tmp_path / "moved.bin"
        os.replace(m.source, moved)
        try:
            assert [x.sha256 for x in r.find(str(m.source))] == [m.sha256]
            assert [x.sha256 for x in r.find(str(tmp_path / "lib_link" / m.path))] == [m.sha256]
            assert r.find(str(moved)) == []
        finally:
            os.replace(moved, m.source)


def test_ambiguous_prefix_is_an_error_listing_the_matches(tmp_path):
    from tests.test_catalog import build, make_entry

    a, b = make_entry(0), make_entry(1)
    a.sha256, b.sha256 = "abcdef01" + "0" * 56, "abcdef01" + "1" * 56
    build(tmp_path / "cat", [a, b]).close()
    with CatalogReader(tmp_path / "cat") as r:
        with pytest.raises(CatalogError, match="2 meshes match 'abcdef01'") as info:
            r.mesh("abcdef01")
        assert "lib/m000.glb" in str(info.value) and "lib/m001.glb" in str(info.value)
        assert r.mesh("abcdef011").path == "lib/m001.glb"


def test_schema_1_catalogue_is_upgraded_by_the_writer(tmp_path):
    """A schema-1 catalogue: the read-only reader says how to upgrade; the writer does it."""
    from tests.test_catalog import build, make_entry
    from ucad_catalog import Catalog

    build(tmp_path / "cat", [make_entry(0)]).close()
    con = sqlite3.connect(tmp_path / "cat" / "catalog.sqlite")
    con.executescript("DROP INDEX meshes_path; ALTER TABLE meshes DROP COLUMN library_root; "
                      "ALTER TABLE meshes DROP COLUMN orientation; ALTER TABLE meshes DROP "
                      "COLUMN meta; CREATE INDEX meshes_path ON meshes(path); "
                      "UPDATE meta SET value='1' WHERE key='schema_version';")
    con.close()
    with pytest.raises(CatalogError, match="schema_version 1.*ucad-index status"):
        CatalogReader(tmp_path / "cat")
    Catalog.open(tmp_path / "cat").close()
    with CatalogReader(tmp_path / "cat") as r:
        (m,) = r.meshes()
        assert (m.path, m.library_root, m.orientation, m.meta) == ("lib/m000.glb", "", None, {})


# ---------------------------------------------------------------------------- one-part decoder
@pytest.mark.parametrize("head_bytes, inflate", [(None, "libdeflate"), (16, "libdeflate"),
                                                  (None, "zlib")])
def test_one_part_decoder_equals_openexr(tmp_path, monkeypatch, head_bytes, inflate):
    """ViewStackFile against OpenEXR's own decoder: ZIP (compressible and incompressible
    chunks), ZIPS, no compression, a single-part file, empty views, parts whose header has
    one more attribute among runs of headers that repeat a layout (``_repeated_headers``
    compares a run at once: it must end at each such part and start again after it); PIZ goes
    through OpenEXR.
    With a 16-byte first read the headers are read in doubling steps (as a long stack's are);
    a stack cut or removed after it was opened gives ValueError naming it at the read. ZIP
    chunks inflate through libdeflate, or through zlib where ``deflate`` is not installed (the
    reader alone)."""
    import OpenEXR

    from ucad_catalog import exr

    if head_bytes is not None:
        monkeypatch.setattr(exr, "_HEAD_BYTES", head_bytes)
    if inflate == "zlib":
        monkeypatch.setitem(sys.modules, "deflate", None)     # import deflate: ImportError
    else:
        pytest.importorskip("deflate")

    rng = np.random.default_rng(3)
    H, W = 37, 29
    for comp in ("ZIP_COMPRESSION", "ZIPS_COMPRESSION", "NO_COMPRESSION", "PIZ_COMPRESSION"):
        for n_parts in (1, 4, 9):
            parts = []
            for v in range(n_parts):
                box = (v % 3, H - (v % 2) * 5, 2 * v, W)       # y0, y1, x0, x1 (half-open)
                h, w = box[1] - box[0], box[3] - box[2]
                if v == 2:
                    h = w = 1
                    box = (0, 1, 0, 1)
                chans = {"tri": rng.integers(0, 2**32, (h, w), dtype=np.uint32),  # noise
                         "mat": np.repeat(rng.integers(0, 5, (h, 1)), w, 1).astype(np.uint32),
                         "Z": rng.random((h, w)).astype(np.float32)}
                header = {"dataWindow": (np.array([box[2], box[0]], np.int32),
                                         np.array([box[3] - 1, box[1] - 1], np.int32)),
                          "displayWindow": (np.array([0, 0], np.int32),
                                            np.array([W - 1, H - 1], np.int32)),
                          "compression": getattr(OpenEXR, comp), "type": OpenEXR.scanlineimage}
                if v in (1, 6):             # a header of another layout among repeated ones
                    header["comments"] = "one more attribute"
                parts.append(OpenEXR.Part(header, {k: OpenEXR.Channel(x)
                                                   for k, x in chans.items()}, f"view_{v:03d}"))
            path = tmp_path / f"{comp}-{n_parts}.exr"
            OpenEXR.File(parts).write(str(path))
            ref = OpenEXR.File(str(path), separate_channels=True).parts
            f = ViewStackFile(path)
            assert f.n_views == n_parts
            for v in range(n_parts):
                got = f.read(v)
                (x0, y0), (x1, y1) = ref[v].header["dataWindow"]
                for c in ("tri", "mat", "Z"):
                    want = ref[v].channels[c].pixels
                    assert np.array_equal(got[c][y0:y1 + 1, x0:x1 + 1], want), (comp, v, c)
                    outside = np.ones((H, W), bool)
                    outside[y0:y1 + 1, x0:x1 + 1] = False
                    bg = {"tri": 0xFFFFFFFF, "mat": 0, "Z": np.inf}[c]
                    assert np.all(got[c][outside] == bg)
                assert got["mat"].dtype == np.uint16 and f.read(v, ("Z",)).keys() == {"Z"}
    with pytest.raises(ValueError, match="no view 9"):
        f.read(9)
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"\x76\x2f\x31\x01" + b"\x02\x00\x00\x00" + b"junk")
    with pytest.raises(ValueError, match="bad.exr"):
        ViewStackFile(bad)
    data = bytearray((tmp_path / "ZIP_COMPRESSION-4.exr").read_bytes())
    data[-40:] = b"\xff" * 40                             # corrupt the last chunk
    (tmp_path / "corrupt.exr").write_bytes(bytes(data))
    with pytest.raises(ValueError, match="corrupt.exr"):
        g = ViewStackFile(tmp_path / "corrupt.exr")
        for v in range(g.n_views):
            g.read(v)
    loop = bytearray((tmp_path / "ZIP_COMPRESSION-4.exr").read_bytes())  # an attribute whose
    first = loop.index(b"\0", loop.index(b"\0", 8) + 1) + 1       # size points back at itself
    loop[first:first + 4] = struct.pack("<i", 8 - (first + 4))
    (tmp_path / "loop.exr").write_bytes(bytes(loop))
    with pytest.raises(ValueError, match="loop.exr: not a readable .* negative size"):
        ViewStackFile(tmp_path / "loop.exr")
    stack = ViewStackFile(tmp_path / "ZIP_COMPRESSION-4.exr")     # a chunk offset past the end
    table = int(stack.parts[0]["offsets"][0]) - 8 * sum(len(p["offsets"]) for p in stack.parts)
    far = bytearray((tmp_path / "ZIP_COMPRESSION-4.exr").read_bytes())
    far[table + 8:table + 16] = struct.pack("<Q", 2**62)          # view 0's second chunk
    (tmp_path / "far.exr").write_bytes(bytes(far))
    with pytest.raises(ValueError, match="far.exr: view 0: corrupt chunk data"):
        ViewStackFile(tmp_path / "far.exr").read(0)
    opened = ViewStackFile(tmp_path / "ZIP_COMPRESSION-4.exr")    # cut after the open
    whole = (tmp_path / "ZIP_COMPRESSION-4.exr").read_bytes()
    (tmp_path / "ZIP_COMPRESSION-4.exr").write_bytes(whole[:len(whole) // 2])
    with pytest.raises(ValueError, match="ZIP_COMPRESSION-4.exr: view 3: corrupt"):
        opened.read(3)
    (tmp_path / "ZIP_COMPRESSION-4.exr").unlink()
    with pytest.raises(ValueError, match="ZIP_COMPRESSION-4.exr: view 0: cannot read"):
        opened.read(0)
    cut = tmp_path / "cut.exr"                                    # cut anywhere: ValueError
    for n in sorted(set(range(0, 600)) | set(range(600, len(whole), 7))):
        cut.write_bytes(whole[:n])
        with pytest.raises(ValueError, match="cut.exr"):
            g = ViewStackFile(cut)
            for v in range(g.n_views):
                g.read(v)


# ---------------------------------------------------------------------------- command line
def test_cli_build_single_mesh_quiet_and_rejection_summary(built, tmp_path, capsys):
    from ucad_cl.cli import main

    lib, _, _ = built
    one = sorted(lib.glob("synth_*.glb"))[0]
    args = ["--azimuth-step", "180", "--size", "32", "--no-features"]
    assert main(["build", str(one), "--catalog", str(tmp_path / "c1"), "-q", *args]) == 0
    out = capsys.readouterr()
    assert out.out == ""                                           # --quiet: nothing on stdout
    with CatalogReader(tmp_path / "c1") as r:
        (m,) = r.meshes()
        assert (m.path, m.library_root) == (one.name, str(lib))
    assert main(["build", str(lib), "--catalog", str(tmp_path / "c2"), *args]) == 0
    out = capsys.readouterr().out
    assert "OpenCL device" in out and "rejected 2 mesh(es), by reason" in out
    assert "too_few_materials" in out and "single.glb" in out and "broken.glb" in out
    log = tmp_path / "c2" / "logs" / "run-00001.log"
    assert f"run log (every mesh, reasons, timings): {log}" in out and log.is_file()


def test_cli_uid_lists(built, tmp_path, capsys):
    from ucad_cl.cli import main

    lib, _, _ = built
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    keep = sorted(p.stem for p in lib.glob("synth_*.glb"))[:2]
    pq.write_table(pa.table({"uid": keep + ["not-there"], "n": [1, 2, 3]}), tmp_path / "u.parquet")
    args = ["--catalog", str(tmp_path / "c"), "--azimuth-step", "180", "--size", "32",
            "--no-features", "-q"]
    assert main(["build", str(lib), "--uids", str(tmp_path / "u.parquet"), *args]) == 0
    with CatalogReader(tmp_path / "c") as r:
        assert sorted(Path(m.path).stem for m in r.meshes(None)) == keep
    pq.write_table(pa.table({"name": ["a"]}), tmp_path / "nouid.parquet")
    (tmp_path / "junk.parquet").write_bytes(b"PAR1 not really")
    (tmp_path / "binary.txt").write_bytes(b"\xff\xfe\x00\x81")
    for f, msg in (("nouid.parquet", "no uid column"), ("junk.parquet", "not a readable Parquet"),
                   ("binary.txt", "not a uid list"), ("missing.txt", "does not exist")):
        assert main(["build", str(lib), "--uids", str(tmp_path / f), *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and f in err and msg in err and "Traceback" not in err
    (tmp_path / "lib.bin").write_bytes(b"\x00\xff\xfe")              # a library that is neither
    assert main(["build", str(tmp_path / "lib.bin"), *args]) == 2
    assert "not a mesh folder, a mesh file" in capsys.readouterr().err


def test_cli_parts_segmenter_spelling_and_stem_clashes(built, tmp_path, capsys):
    from ucad_cl.cli import main

    lib, _, _ = built
    car = sorted(lib.glob("synth_*.glb"))[0]
    small = ["--azimuth-step", "180", "--size", "32", "--out", str(tmp_path / "p")]
    assert main(["parts", "--segmenter", "prior", str(car), *small]) == 0   # mesh not swallowed
    assert (tmp_path / "p" / f"{car.stem}.parts.csv").exists()
    assert main(["parts", str(car), "--segmenter", "masks", *small]) == 2
    assert "unknown segmenter 'masks'" in capsys.readouterr().err
    twin = tmp_path / "other" / car.name
    twin.parent.mkdir()
    twin.write_bytes(car.read_bytes())
    for cmd in (["render", str(car), str(twin), "--out", str(tmp_path / "r"), "--size", "32"],
                ["parts", str(car), str(twin), *small[:-1], str(tmp_path / "r")]):
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert "two inputs would write the same outputs" in err and str(twin) in err
        assert not (tmp_path / "r").exists()                             # nothing written


def test_sheet_labels_draw_a_degree_sign():
    """Labels say 'az 30° el 15°'; OpenCV's font has no '°' (it draws '?'): ours draws a ring."""
    import cv2

    from ucad_cl.cameras import make_ring
    from ucad_cl.sheets import DEGREE, put_label, view_labels

    labels = view_labels(make_ring(azimuths=[30.0], elevations=[15.0], size=8))
    assert labels == [f"az 30{DEGREE} el 15{DEGREE}"]
    ours = np.zeros((20, 60, 3), np.uint8)
    put_label(ours, f"30{DEGREE}", (2, 15))
    plain = np.zeros_like(ours)
    cv2.putText(plain, "30", (2, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (230, 230, 230), 1,
                cv2.LINE_AA)
    question = np.zeros_like(ours)
    cv2.putText(question, "30?", (2, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (230, 230, 230), 1,
                cv2.LINE_AA)
    w = cv2.getTextSize("30", cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)[0][0] + 2
    assert np.array_equal(ours[:, :w], plain[:, :w])                  # the digits unchanged
    ring = ours[:, w:].max(axis=2) > 0
    ys, xs = np.nonzero(ring)
    assert ring.sum() >= 4 and ys.max() <= 15 - 4                     # a raised mark...
    assert not np.array_equal(ours, question)                         # ... that is not '?'


def test_info_names_the_device_and_why(capsys):
    from ucad_cl.cli import main
    from ucad_cl.runtime import device_infos, device_rank, get_runtime

    assert main(["info"]) == 0
    out = capsys.readouterr().out
    rt = get_runtime()
    assert f"in use: {rt.info.spec} " in out and f"why: {rt.why}" in out
    infos = device_infos()
    if not os.environ.get("UCAD_CL_DEVICE") and len(infos) > 1:
        # the chosen device is the best-ranked usable one: every better-ranked one is unusable,
        # named with its reason, and listed as such
        better = [i for i in infos if device_rank(i) < device_rank(rt.info)]
        assert all(f"{i.spec} {i.device} is unusable (" in rt.why for i in better)
        assert all(f"{i.spec}  unusable" in out for i in better)
