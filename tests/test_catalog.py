"""Catalogue store and reader: round trip, crash atomicity (SIGKILL), re-processing policy,
WAL concurrency, no-OpenCL import, export, errors, exact nearest-view search.

References are independent of the code under test: raw ``sqlite3`` queries, ``hashlib`` over the
object files, NumPy arrays kept by the test, brute-force Python loops.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ucad_catalog import (SCHEMA_VERSION, Catalog, CatalogEntry, CatalogError, CatalogReader,
                          MaterialRow, ViewRow, options_hash)

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("features.npy", "views.npz")
PARTS = ("body", "window", "wheel")


# ---------------------------------------------------------------------------- fixtures
def make_entry(i: int, n_views: int = 3, h: int = 6, w: int = 7, d: int = 8, blob: int = 0,
               path: str | None = None, tag: str = "") -> CatalogEntry:
    """Deterministic entry number ``i``; ``blob`` adds a random artifact of that many bytes."""
    rng = np.random.default_rng(i)
    n_mat = 3
    mat_id = rng.integers(0, n_mat + 1, size=(n_views, h, w)).astype(np.uint16)
    tri_id = np.where(mat_id == 0, np.uint32(0xFFFFFFFF),
                      rng.integers(0, 1000, size=(n_views, h, w))).astype(np.uint32)
    depth = np.where(mat_id == 0, np.inf, rng.random((n_views, h, w)) + 1).astype(np.float32)
    feats = rng.standard_normal((n_views, d)).astype(np.float32)
    arts: dict = {"views.npz": _npz(tri_id=tri_id, mat_id=mat_id, depth=depth),
                  "features.npy": _npy(feats)}
    if blob:
        arts["blob.bin"] = rng.bytes(blob)
    mats = [MaterialRow(m, f"mat_{m}_ü", PARTS[m % 3], float(rng.random()), float(rng.random()),
                        m % n_views, "best-view", int(rng.integers(0, 999)),
                        {"metallic": np.float32(0.5), "rgb": np.array([0.1, 0.2, 1 / 3])})
            for m in range(n_mat)]
    views = [ViewRow(v, 360.0 * v / n_views, 15.0, rng.standard_normal((3, 3)),
                     rng.standard_normal((4, 4)), {"coverage": float(rng.random())})
             for v in range(n_views)]
    return CatalogEntry(sha256=hashlib.sha256(f"mesh-{i}{tag}".encode()).hexdigest(),
                        path=path or f"lib/m{i:03d}.glb", size=1000 + i, mtime=1.7e9 + i / 3,
                        n_triangles=100 + i, n_materials=n_mat,
                        file_to_norm=rng.standard_normal((4, 4)), materials=mats, views=views,
                        artifacts=arts, timings={"render": 0.25 * i})


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _arrays(entry: CatalogEntry) -> dict:
    with np.load(io.BytesIO(entry.artifacts["views.npz"])) as z:
        return {k: z[k] for k in z.files}


def build(root: Path, entries, options=None, durable: bool = True) -> Catalog:
    cat = Catalog.open(root, durable=durable)
    run = cat.begin_run(options or {"size": 8}, "test")
    for e in entries:
        cat.commit_mesh(e)
    cat.finish_run(run)
    return cat


def dump(root: Path) -> dict:
    """Independent content dump: every row (minus run bookkeeping) + every object's real hash."""
    con = sqlite3.connect(root / "catalog.sqlite")
    out = {
        "meshes": con.execute("SELECT id, sha256, path, size, mtime, state, reason, detail, "
                              "n_triangles, n_materials, file_to_norm, options_hash, timings "
                              "FROM meshes ORDER BY id").fetchall(),
        "materials": con.execute("SELECT * FROM materials ORDER BY mesh_id, idx").fetchall(),
        "views": con.execute("SELECT * FROM views ORDER BY mesh_id, view").fetchall(),
        "artifacts": con.execute("SELECT * FROM artifacts ORDER BY mesh_id, kind").fetchall(),
    }
    con.close()
    out["objects"] = sorted(
        (p.name, hashlib.sha256(p.read_bytes()).hexdigest())
        for p in (root / "objects").glob("*/*") if not p.name.startswith("."))
    return out


def check_consistent(root: Path, expected: dict[str, CatalogEntry]) -> int:
    """Every committed mesh complete (rows + objects with matching sha256), no partial rows."""
    con = sqlite3.connect(root / "catalog.sqlite")
    try:
        for table in ("materials", "views", "artifacts"):
            assert con.execute(f"SELECT count(*) FROM {table} WHERE mesh_id NOT IN "
                               "(SELECT id FROM meshes)").fetchone()[0] == 0, table
        rows = con.execute("SELECT id, sha256 FROM meshes").fetchall()
        for mid, sha in rows:
            e = expected[sha]
            n_mat = con.execute("SELECT count(*) FROM materials WHERE mesh_id=?",
                                (mid,)).fetchone()[0]
            n_view = con.execute("SELECT count(*) FROM views WHERE mesh_id=?",
                                 (mid,)).fetchone()[0]
            assert (n_mat, n_view) == (len(e.materials), len(e.views)), sha
            arts = dict(((k, (s, n)) for k, s, n in con.execute(
                "SELECT kind, sha256, bytes FROM artifacts WHERE mesh_id=?", (mid,))))
            assert sorted(arts) == sorted(e.artifacts), sha
            for kind, (s, n) in arts.items():
                data = (root / "objects" / s[:2] / s).read_bytes()
                assert hashlib.sha256(data).hexdigest() == s and len(data) == n
                assert data == bytes(e.artifacts[kind])
        return len(rows)
    finally:
        con.close()


# ---------------------------------------------------------------------------- round trip
def test_round_trip_full_entry(tmp_path):
    entries = [make_entry(i) for i in range(3)]
    rej = make_entry(9)
    rej.state, rej.reason, rej.detail = "rejected", "too-few-materials", "1 material"
    rej.materials, rej.views, rej.artifacts = [], [], {}
    build(tmp_path / "cat", entries + [rej]).close()

    with CatalogReader(tmp_path / "cat") as r:
        infos = r.meshes()
        assert [m.sha256 for m in infos] == [e.sha256 for e in entries]
        assert [m.sha256 for m in r.meshes("rejected")] == [rej.sha256]
        assert len(r.meshes(None)) == 4
        e, m = entries[1], infos[1]
        assert (m.path, m.size, m.mtime, m.n_triangles) == (e.path, e.size, e.mtime, 101)
        assert np.array_equal(m.file_to_norm, e.file_to_norm)          # bit-exact float64
        assert m.timings == {"render": 0.25}
        parts = r.parts(e.sha256)
        assert [(p.name, p.part, p.score, p.iou, p.view, p.pixels) for p in parts] == \
            [(x.name, x.part, x.score, x.iou, x.view, x.pixels) for x in e.materials]
        assert parts[0].props == {"metallic": 0.5, "rgb": [0.1, 0.2, 1 / 3]}
        name, part, score, *_ = parts[2]
        assert (name, part) == ("mat_2_ü", "wheel")

        ref = _arrays(e)
        for v in range(3):
            rec = r.view(e.sha256, v)
            assert np.array_equal(rec.K, e.views[v].K) and np.array_equal(rec.w2c, e.views[v].w2c)
            assert (rec.azimuth, rec.elevation) == (e.views[v].azimuth, 15.0)
            assert np.array_equal(rec.mat_id, ref["mat_id"][v])
            assert np.array_equal(rec.tri_id, ref["tri_id"][v])
            assert np.array_equal(rec.depth, ref["depth"][v])
            assert rec.stats == e.views[v].stats
            assert sorted(rec.part_masks) == sorted(PARTS)
            for part, mask in rec.part_masks.items():   # reference: pixel loop over the table
                ids = {x.index + 1 for x in e.materials if x.part == part}
                want = np.array([[px in ids for px in row] for row in ref["mat_id"][v]])
                assert mask.dtype == bool and np.array_equal(mask, want)
        np.testing.assert_array_equal(r.features(e.sha256),
                                      np.load(io.BytesIO(e.artifacts["features.npy"])))
        for kind in KINDS:
            assert r.artifact_path(e.sha256, kind).read_bytes() == e.artifacts[kind]
        con = sqlite3.connect(tmp_path / "cat" / "catalog.sqlite")
        assert con.execute("SELECT sha256, reason FROM rejections").fetchall() == \
            [(rej.sha256, "too-few-materials")]
    assert check_consistent(tmp_path / "cat", {x.sha256: x for x in entries + [rej]}) == 4


def test_status_counts_and_same_input_same_bytes(tmp_path):
    entries = [make_entry(i) for i in range(4)]
    for i, reason in ((1, "no-wheels"), (2, "no-wheels"), (3, "broken")):
        entries[i].state, entries[i].reason = "rejected", reason
    a, b = build(tmp_path / "a", entries), build(tmp_path / "b", entries, durable=False)
    st = a.status()
    assert st["meshes"] == 4 and st["by_state"] == {"accepted": 1, "rejected": 3}
    assert st["by_reason"] == {"broken": 1, "no-wheels": 2}
    assert st["last_run"]["counts"] == {"accepted": 1, "rejected": 3}
    assert st["last_run"]["meshes_per_s"] > 0 and st["schema_version"] == SCHEMA_VERSION
    a.export(tmp_path / "a.jsonl")
    b.export(tmp_path / "b.jsonl")
    assert (tmp_path / "a.jsonl").read_bytes() == (tmp_path / "b.jsonl").read_bytes()
    assert dump(tmp_path / "a") == dump(tmp_path / "b")
    a.close(), b.close()


# ---------------------------------------------------------------------------- atomicity
WRITER = """
import sys, time
sys.path.insert(0, {root!r})
from tests.test_catalog import make_entry
from ucad_catalog import Catalog, options_hash
cat = Catalog.open(sys.argv[1])
opts = {{"size": 8}}
run = cat.begin_run(opts, "writer")
print("started", flush=True)
for i in range(int(sys.argv[2])):
    e = make_entry(i, blob=int(sys.argv[3]))
    if cat.needs_processing(e.path, e.sha256, options_hash(opts)):
        cat.commit_mesh(e)
        time.sleep(float(sys.argv[4]))
cat.finish_run(run)
print("done", flush=True)
"""


def _writer(tmp_path: Path, root: Path, n: int, blob: int, pause: float) -> subprocess.Popen:
    script = tmp_path / "writer.py"
    script.write_text(WRITER.format(root=str(ROOT)))
    return subprocess.Popen([sys.executable, str(script), str(root), str(n), str(blob),
                             str(pause)], stdout=subprocess.PIPE, text=True, cwd=ROOT)


def test_sigkill_at_random_moments_leaves_whole_meshes(tmp_path):
    n, blob = 50, 400_000            # a few ms per commit, mostly spent writing objects
    expected = {e.sha256: e for e in (make_entry(i, blob=blob) for i in range(n))}
    crashed, rnd = tmp_path / "crashed", random.Random(1234)
    killed_alive = orphaned = extra_before = 0
    for _ in range(12):
        p = _writer(tmp_path, crashed, n, blob, 0.0)
        assert p.stdout.readline().strip() == "started"
        time.sleep(rnd.uniform(0.0, 0.05))
        killed_alive += p.poll() is None
        p.send_signal(signal.SIGKILL)             # no-op if it already finished
        p.wait()
        committed = check_consistent(crashed, expected)   # nothing partial after any kill
        n_objects = sum(1 for _ in (crashed / "objects").glob("*/*"))
        extra = n_objects - committed * 3                 # written but not (yet) committed
        orphaned += extra > extra_before
        extra_before = extra
    print(f"kills of a running writer: {killed_alive}/12, kills leaving orphans: {orphaned}")
    assert killed_alive >= 6                      # the kills really interrupted running writers
    assert orphaned >= 1                          # and some hit between objects and commit
    p = _writer(tmp_path, crashed, n, blob, 0.0)
    assert p.communicate(timeout=60)[0].split() == ["started", "done"]
    assert check_consistent(crashed, expected) == n
    with Catalog.open(crashed) as cat:
        cat.gc()
        assert cat.verify() == []

    clean = tmp_path / "clean"
    p = _writer(tmp_path, clean, n, blob, 0.0)
    assert p.communicate(timeout=60)[0].split() == ["started", "done"]
    assert dump(crashed) == dump(clean)           # same rows, ids, artifact hashes; no orphans


def _commit_killed(root: Path, entry: CatalogEntry, opts: dict, at_stmt: int = 0,
                   at_rename: int = 0) -> int:
    """Fork a writer that SIGKILLs itself before SQL statement ``at_stmt`` of ``commit_mesh``
    (sqlite3 trace callback) or right after its ``at_rename``-th object rename; returns the
    number of statements the commit ran (when not killed)."""
    import shutil
    count = [0]
    pid = os.fork()
    if pid == 0:                                   # child: never returns to pytest
        try:
            import ucad_catalog.store as store
            cat = Catalog.open(root)
            cat.begin_run(opts, "killed")
            real_replace, renames = store.os.replace, [0]

            def replace(a, b):
                real_replace(a, b)
                renames[0] += 1
                if renames[0] == at_rename:
                    os.kill(os.getpid(), signal.SIGKILL)

            def trace(_sql):
                count[0] += 1
                if count[0] == at_stmt:
                    os.kill(os.getpid(), signal.SIGKILL)
            store.os.replace = replace
            cat._conn.set_trace_callback(trace)
            cat.commit_mesh(entry)
            os._exit(min(count[0], 250))
        except BaseException:
            os._exit(255)
    _, status = os.waitpid(pid, 0)
    if at_stmt or at_rename:
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL
        return 0
    assert os.WIFEXITED(status) and 0 < os.WEXITSTATUS(status) < 250
    shutil.rmtree(root)                        # the dry run's copy is thrown away
    return os.WEXITSTATUS(status)


@pytest.mark.parametrize("scenario", ["new-content-at-old-path", "same-content-new-options"])
def test_kill_before_every_statement_and_after_every_rename(tmp_path, scenario):
    import shutil
    base = [make_entry(0), make_entry(1)]
    build(tmp_path / "base", base, {"size": 8}).close()
    if scenario == "new-content-at-old-path":   # commit = DELETE old row + INSERT new rows
        target, opts = make_entry(7, path=base[0].path), {"size": 8}
    else:                                       # commit = UPDATE row in place + rewrite children
        target, opts = make_entry(1), {"size": 16}
        target.materials[0].part = "rim"
        target.artifacts["features.npy"] = _npy(np.zeros((3, 8), np.float32))
    expected_before = {e.sha256: e for e in base}
    work = tmp_path / "work"
    shutil.copytree(tmp_path / "base", work)
    n_stmt = _commit_killed(work, target, opts)
    assert n_stmt >= 10
    new_objects = [k for k, v in target.artifacts.items() if not (
        tmp_path / "base" / "objects" / _sha(v)[:2] / _sha(v)).exists()]
    assert len(new_objects) == (2 if scenario == "new-content-at-old-path" else 1)
    kills = [(k, 0) for k in range(1, n_stmt + 1)] + [(0, r + 1) for r in range(len(new_objects))]
    for at_stmt, at_rename in kills:
        shutil.copytree(tmp_path / "base", work)
        _commit_killed(work, target, opts, at_stmt, at_rename)
        assert check_consistent(work, expected_before) == 2, (at_stmt, at_rename)
        assert dump(work)["meshes"] == dump(tmp_path / "base")["meshes"]     # old state intact
        with Catalog.open(work) as cat:        # the interrupted commit, redone, completes
            cat.begin_run(opts, "redo")
            assert cat.needs_processing(target.path, target.sha256, options_hash(opts))
            cat.commit_mesh(target)
        after = {e.sha256: e for e in base if e.path != target.path and e.sha256 != target.sha256}
        after[target.sha256] = target
        assert check_consistent(work, after) == 2
        shutil.rmtree(work)


def test_failed_commit_leaves_no_rows_and_gc_collects_orphans(tmp_path):
    with Catalog.open(tmp_path / "cat") as cat:
        cat.begin_run({}, "test")
        good = make_entry(0)
        cat.commit_mesh(good)
        bad = make_entry(1, blob=5000)
        bad.materials[1].props = {"obj": object()}          # fails inside the transaction
        with pytest.raises(TypeError):
            cat.commit_mesh(bad)
        check_consistent(tmp_path / "cat", {good.sha256: good})
        stray = tmp_path / "cat" / "objects" / "ab" / ".tmp-deadbeef.1.x"
        stray.parent.mkdir(exist_ok=True)
        stray.write_bytes(b"half")
        before = {p.name for p in (tmp_path / "cat" / "objects").glob("*/*")}
        stats = cat.gc()
        after = {p.name for p in (tmp_path / "cat" / "objects").glob("*/*")}
        referenced = {hashlib.sha256(bytes(v)).hexdigest() for v in good.artifacts.values()}
        assert after == referenced
        assert stats["tmp_removed"] == 1 and stats["objects_removed"] == len(before) - 3
        assert stats["objects_removed"] == 3                  # bad's 3 objects written, orphaned
        assert cat.verify() == []


def test_move_files_renames_staged_artifacts_into_the_store(tmp_path):
    """``move_files``: a staged file becomes the object (same bytes, source gone); a second
    file with content already stored is just removed; without it the file is copied."""
    root = tmp_path / "cat"
    staging = root / "staging"
    payload = np.random.default_rng(0).bytes(3 * (1 << 20) + 17)     # several copy chunks
    with Catalog.open(root) as cat:
        staging.mkdir()
        cat.begin_run({}, "test")
        for i, move in ((0, True), (1, True), (2, False)):
            src = staging / f"m{i}.views.exr"
            src.write_bytes(payload)
            e = make_entry(i)
            e.artifacts["views.exr"] = src
            cat.commit_mesh(e, move_files=move)
            assert src.exists() is (not move)
        obj = root / "objects" / _sha(payload)[:2] / _sha(payload)
        assert obj.read_bytes() == payload
        assert cat.verify() == []
    with CatalogReader(root) as r:
        assert all(r.artifact_path(m.sha256, "views.exr").read_bytes() == payload
                   for m in r.meshes())


# ---------------------------------------------------------------------------- policy
def test_needs_processing_policy(tmp_path):
    opts_a, opts_b = {"size": 8, "runtime": {"jobs": 1}}, {"size": 16}
    ha, hb = options_hash(opts_a), options_hash(opts_b)
    assert ha == options_hash({"size": 8, "runtime": {"jobs": 4}})   # runtime is not hashed
    assert ha != hb
    cat = Catalog.open(tmp_path / "cat")
    cat.begin_run(opts_a, "test")
    e0, e1 = make_entry(0), make_entry(1)
    e1.state, e1.reason, e1.artifacts = "rejected", "no-wheels", {}
    assert cat.needs_processing(e0.path, e0.sha256, ha)
    id0, id1 = cat.commit_mesh(e0), cat.commit_mesh(e1)
    assert not cat.needs_processing(e0.path, e0.sha256, ha)           # unchanged: skip
    assert not cat.needs_processing(e1.path, e1.sha256, ha)           # rejection is a result
    assert cat.file_record(e0.path) == (e0.sha256, e0.size, e0.mtime)

    changed = make_entry(5, path=e0.path)                             # same path, new content
    assert cat.needs_processing(changed.path, changed.sha256, ha)
    cat.commit_mesh(changed)
    with CatalogReader(tmp_path / "cat") as r:
        # listed by path: changed took e0's path lib/m000.glb, e1 is lib/m001.glb
        assert [m.sha256 for m in r.meshes(None)] == [changed.sha256, e1.sha256]
        with pytest.raises(CatalogError, match="no mesh"):
            r.parts(e0.sha256)

    cat.begin_run(opts_b, "test")                                     # result options changed
    assert cat.needs_processing(e1.path, e1.sha256, hb)
    e1b = make_entry(1)                                               # now accepted
    assert cat.commit_mesh(e1b) == id1                                # replaced in place
    assert not cat.needs_processing(e1.path, e1.sha256, hb)
    con = sqlite3.connect(tmp_path / "cat" / "catalog.sqlite")
    assert con.execute("SELECT count(*), state, options_hash FROM meshes WHERE sha256=?",
                       (e1.sha256,)).fetchone() == (1, "accepted", hb)
    assert con.execute("SELECT count(*) FROM meshes").fetchone()[0] == 2
    assert id0 not in [r[0] for r in con.execute("SELECT id FROM meshes")]
    cat.close()
    check_consistent(tmp_path / "cat", {e.sha256: e for e in (e1b, changed)})


# ---------------------------------------------------------------------------- concurrency
def test_reader_snapshot_while_writer_commits(tmp_path):
    cat = build(tmp_path / "cat", [make_entry(0)])
    r = CatalogReader(tmp_path / "cat")
    cat.begin_run({"size": 8}, "test")
    with r.snapshot():
        assert len(r.meshes()) == 1
        cat.commit_mesh(make_entry(1))                 # the writer is not blocked by the reader
        assert len(r.meshes()) == 1                    # and the snapshot does not move
    assert len(r.meshes()) == 2
    r.close(), cat.close()


def test_wal_reader_in_parallel_with_writer_process(tmp_path):
    n = 25
    expected = {e.sha256: e for e in (make_entry(i) for i in range(n))}
    root = tmp_path / "cat"
    build(root, []).close()
    p = _writer(tmp_path, root, n, 0, 0.01)
    assert p.stdout.readline().strip() == "started"
    r, seen = CatalogReader(root), []
    while True:
        running = p.poll() is None
        with r.snapshot():
            metas = r.meshes()
            for m in metas:                            # every visible mesh is complete
                rec = r.record(m.sha256)
                e = expected[m.sha256]
                assert (len(rec["materials"]), len(rec["views"])) == (3, 3)
                assert sorted(rec["artifacts"]) == sorted(e.artifacts)
        seen.append(len(metas))
        if not running:
            break
    p.wait()
    assert seen == sorted(seen) and seen[-1] == n      # monotone, complete at the end
    assert any(0 < s < n for s in seen)                # really read during the writes
    r.close()


def test_reader_imports_no_pyopencl(tmp_path):
    from ucad_catalog.exr import write_viewset_exr
    from ucad_cl.artifacts import CameraRing, ViewSet

    a, b = make_entry(0), make_entry(1)
    arr = _arrays(b)
    ring = CameraRing(b.views[0].K, np.stack([v.w2c for v in b.views]), 7, 6,
                      np.array([v.azimuth for v in b.views]), np.full(3, 15.0), 2.0, 0.1)
    exr = write_viewset_exr(tmp_path / "b.exr", ViewSet(ring, arr["tri_id"], arr["mat_id"],
                                                        arr["depth"]), material_names=["x"] * 3)
    b.artifacts = {"views.exr": exr, "features.npy": b.artifacts["features.npy"]}
    build(tmp_path / "cat", [a, b]).close()
    np.save(tmp_path / "m.npy", arr["mat_id"][2])
    code = f"""
import sys
sys.modules["pyopencl"] = None          # any import of pyopencl now raises ImportError
import ucad_catalog, ucad_catalog.reader, ucad_catalog.store, ucad_catalog.entry
from pathlib import Path
if (Path(ucad_catalog.__file__).parent / "exr.py").exists():
    import ucad_catalog.exr
import numpy as np
r = ucad_catalog.CatalogReader({str(tmp_path / 'cat')!r})
npz, exr = (m.sha256 for m in r.meshes())
assert r.view(npz, 1).mat_id.shape == (6, 7) and r.nearest_views(r.features(npz)[0], 1)
assert np.array_equal(r.view(exr, 2).mat_id, np.load({str(tmp_path / 'm.npy')!r})), "exr"
bad = [m for m in sys.modules if m.startswith("pyopencl") and sys.modules[m] is not None]
assert not bad and "ucad_cl.runtime" not in sys.modules, bad
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=tmp_path, timeout=60)
    assert out.stdout.strip() == "ok", out.stderr


# ---------------------------------------------------------------------------- export
def test_export_jsonl_round_trip(tmp_path):
    """Meshes table + materials table, values equal to the entries committed (independent
    reference: the CatalogEntry objects), metadata sidecar, same bytes twice."""
    entries = [make_entry(i) for i in (2, 0, 1)]
    entries[0].orientation = {"rotation": np.eye(3), "up_confidence": 0.9}
    entries[0].meta = {"source": "test"}
    cat = build(tmp_path / "cat", entries)
    assert cat.export(tmp_path / "out.jsonl") == 3
    recs = [json.loads(x) for x in (tmp_path / "out.jsonl").read_text("utf-8").splitlines()]
    mats = [json.loads(x) for x in
            (tmp_path / "out.materials.jsonl").read_text("utf-8").splitlines()]
    by_path = sorted(entries, key=lambda e: e.path)
    assert [r["id"] for r in recs] == [e.sha256 for e in by_path]     # listed by path
    for rec, e in zip(recs, by_path):
        assert (rec["path"], rec["mtime"], rec["export_version"]) == (e.path, e.mtime, 1)
        assert np.array_equal(np.array(rec["file_to_norm"]).reshape(4, 4), e.file_to_norm)
        assert [np.array_equal(np.array(v["w2c"]).reshape(4, 4), x.w2c) for v, x in
                zip(rec["views"], e.views)] == [True] * 3
        assert {a["kind"]: a["sha256"] for a in rec["artifacts"]} == \
            {k: hashlib.sha256(v).hexdigest() for k, v in e.artifacts.items()}
        assert "timings" not in rec and "run_id" not in rec           # not content
    assert recs[2]["orientation"] == {"rotation": np.eye(3).tolist(), "up_confidence": 0.9}
    assert recs[0]["orientation"] is None and recs[2]["meta"] == {"source": "test"}
    assert [(m["mesh_id"], m["index"], m["name"], m["part"]) for m in mats] == \
        [(e.sha256, x.index, x.name, x.part) for e in by_path for x in e.materials]
    assert mats[0]["metallic"] == 0.5 and mats[0]["base_color"] is None   # typed from props
    meta = json.loads((tmp_path / "out.jsonl.meta.json").read_text())
    assert meta["ucad:export_version"] == "1" and "canonical frame" in meta["ucad:conventions"]
    first = (tmp_path / "out.jsonl").read_bytes()
    cat.export(tmp_path / "out.jsonl")
    assert (tmp_path / "out.jsonl").read_bytes() == first
    with pytest.raises(CatalogError, match="jsonl"):
        cat.export(tmp_path / "out.csv", format="csv")
    with pytest.raises(CatalogError, match="suffix"):
        cat.export(tmp_path / "out.csv")
    cat.close()


def test_export_parquet_schema_concatenates_and_carries_metadata(tmp_path, monkeypatch):
    """An all-rejected catalogue and a normal one export the same schema (concat_tables joins
    them), with the export version and conventions in the file metadata; the suffix picks the
    format; without pyarrow, a clear error."""
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    cat = build(tmp_path / "cat", [make_entry(0), make_entry(1)])
    rej = make_entry(5)
    rej.state, rej.reason, rej.materials, rej.views, rej.artifacts = "rejected", "empty", [], \
        [], {}
    bad = build(tmp_path / "bad", [rej])
    assert cat.export(tmp_path / "a.parquet") == 2
    assert bad.export(tmp_path / "b.parquet") == 1
    a, b = pq.read_table(tmp_path / "a.parquet"), pq.read_table(tmp_path / "b.parquet")
    assert a.schema.equals(b.schema, check_metadata=True)
    both = pa.concat_tables([a, b])
    assert both.column("id").to_pylist() == [make_entry(0).sha256, make_entry(1).sha256,
                                             rej.sha256]
    assert both.column("state").to_pylist() == ["accepted", "accepted", "rejected"]
    ma = pq.read_table(tmp_path / "a.materials.parquet")
    mb = pq.read_table(tmp_path / "b.materials.parquet")
    assert mb.num_rows == 0 and pa.concat_tables([ma, mb]).num_rows == 6
    assert ma.column("name").to_pylist()[2] == "mat_2_ü"
    md = a.schema.metadata
    assert md[b"ucad:export_version"] == b"1" and md[b"ucad:table"] == b"meshes"
    assert b"+Y up" in md[b"ucad:conventions"] and md[b"ucad:catalog_schema_version"] == \
        str(SCHEMA_VERSION).encode()
    views = a.column("views").to_pylist()[0]
    assert np.array_equal(np.array(views[1]["w2c"]).reshape(4, 4), make_entry(0).views[1].w2c)
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    with pytest.raises(CatalogError, match="pyarrow"):
        cat.export(tmp_path / "x.parquet")
    cat.close(), bad.close()


# ---------------------------------------------------------------------------- search
def test_nearest_views_exact_with_tie_rule(tmp_path):
    entries = [make_entry(i, n_views=5, d=6) for i in range(4)]
    entries[2].state, entries[2].reason = "rejected", "x"       # not searched
    f0 = np.load(io.BytesIO(entries[0].artifacts["features.npy"]))
    f3 = f0.copy()
    f3[[1, 4]] = f0[3]                          # duplicates: ties within and across meshes
    entries[3].artifacts["features.npy"] = _npy(f3)
    build(tmp_path / "cat", entries).close()
    r = CatalogReader(tmp_path / "cat")
    q = f0[3].astype(np.float64)
    got = r.nearest_views(q, 4)
    first, second = sorted([entries[0].sha256, entries[3].sha256])   # ties: lower sha256, view
    want = {entries[0].sha256: [3], entries[3].sha256: [1, 3, 4]}
    assert [(s, v, d) for s, v, d in got[:4]] == \
        [(x, v, 0.0) for x in (first, second) for v in want[x]][:4]
    rng = np.random.default_rng(7)
    for _ in range(5):                          # brute force reference, python loop
        q = rng.standard_normal(6)
        ref = []
        for e in entries:
            if e.state != "accepted":
                continue
            f = np.load(io.BytesIO(e.artifacts["features.npy"])).astype(np.float64)
            for v in range(f.shape[0]):                 # ties: lower (sha256, view)
                ref.append((sum((float(a) - float(b)) ** 2 for a, b in zip(f[v], q)),
                            e.sha256, v, e.sha256))
        ref.sort()
        got = r.nearest_views(q, 7)
        assert [(s, v) for s, v, _ in got] == [(x[3], x[2]) for x in ref[:7]]
        np.testing.assert_allclose([d for *_, d in got], [x[0] for x in ref[:7]], rtol=1e-12)
        assert r.nearest_views(q, 7) == got     # deterministic
        one = r.nearest_views(q, 100, sha=entries[1].sha256)
        assert len(one) == 5 and {s for s, *_ in one} == {entries[1].sha256}
    with pytest.raises(CatalogError, match="D=3"):
        r.nearest_views(np.zeros(3), 1)
    with pytest.raises(CatalogError, match="k must"):
        r.nearest_views(np.zeros(6), 0)
    with pytest.raises(CatalogError, match="finite"):
        r.nearest_views(np.full(6, np.nan), 1)
    r.close()


# ---------------------------------------------------------------------------- errors
def test_clear_errors_for_bad_paths(tmp_path):
    missing = tmp_path / "nope"
    with pytest.raises(CatalogError, match="does not exist"):
        CatalogReader(missing)
    with pytest.raises(CatalogError, match="does not exist"):
        Catalog.open(missing, create=False)
    (tmp_path / "file").write_text("x")
    for fn in (CatalogReader, Catalog.open):
        with pytest.raises(CatalogError, match="is a file"):
            fn(tmp_path / "file")
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "photo.jpg").write_bytes(b"x")
    with pytest.raises(CatalogError, match="has no catalog.sqlite"):
        CatalogReader(tmp_path / "plain")
    with pytest.raises(CatalogError, match="not empty"):
        Catalog.open(tmp_path / "plain")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "catalog.sqlite").write_bytes(b"not sqlite at all" * 100)
    for fn in (CatalogReader, Catalog.open):
        with pytest.raises(CatalogError, match="not a ucad catalogue"):
            fn(tmp_path / "junk")
    (tmp_path / "foreign").mkdir()
    con = sqlite3.connect(tmp_path / "foreign" / "catalog.sqlite")
    con.execute("CREATE TABLE t (x)")
    con.commit(), con.close()
    for fn in (CatalogReader, Catalog.open):
        with pytest.raises(CatalogError, match="not a ucad catalogue"):
            fn(tmp_path / "foreign")
    build(tmp_path / "old", []).close()
    con = sqlite3.connect(tmp_path / "old" / "catalog.sqlite")
    con.execute("UPDATE meta SET value='99' WHERE key='schema_version'")
    con.commit(), con.close()
    with pytest.raises(CatalogError, match="schema_version 99"):
        CatalogReader(tmp_path / "old")


def test_clear_errors_for_bad_use_and_entries(tmp_path):
    cat = Catalog.open(tmp_path / "cat")
    with pytest.raises(CatalogError, match="another process|single writer"):
        Catalog.open(tmp_path / "cat")
    with pytest.raises(CatalogError, match="before begin_run"):
        cat.commit_mesh(make_entry(0))
    cat.begin_run({}, "test")

    def bad(**change):
        e = make_entry(0)
        for k, v in change.items():
            setattr(e, k, v)
        return e
    cases = [
        (bad(sha256="ABC"), "64 lowercase hex"),
        (bad(state="maybe"), "state must be"),
        (bad(state="rejected"), "needs a reason"),
        (bad(file_to_norm=np.eye(3)), "file_to_norm must be"),
        (bad(artifacts={"x": 3}), "must be bytes or a Path"),
        (bad(artifacts={"x": tmp_path / "gone.bin"}), "does not exist"),
        (bad(artifacts={"a/b": b""}), "bad artifact kind"),
    ]
    e = make_entry(0)
    e.views[1].w2c = np.full((4, 4), np.nan)
    cases.append((e, "view 1 w2c has non-finite"))
    e = make_entry(0)
    e.materials[2].index = 0
    cases.append((e, "material index 0 appears twice"))
    for entry, msg in cases:
        with pytest.raises(CatalogError, match=msg) as info:
            cat.commit_mesh(entry)
        assert entry.path in str(info.value)
    assert cat.status()["meshes"] == 0

    good = make_entry(0)
    f = tmp_path / "f.npy"
    f.write_bytes(good.artifacts["features.npy"])
    good.artifacts["features.npy"] = f                     # artifact from a file
    cat.commit_mesh(good)
    r = CatalogReader(tmp_path / "cat")
    assert r.artifact_path(good.sha256, "features.npy").read_bytes() == f.read_bytes()
    with pytest.raises(CatalogError, match="no mesh with sha256"):
        r.parts("0" * 64)
    with pytest.raises(CatalogError, match="no artifact 'edges.png-sheet'"):
        r.artifact_path(good.sha256, "edges.png-sheet")
    with pytest.raises(CatalogError, match="no view 7"):
        r.view(good.sha256, 7)
    with pytest.raises(CatalogError, match="state must be"):
        r.meshes("pending")
    r.artifact_path(good.sha256, "views.npz").unlink()
    with pytest.raises(CatalogError, match="missing from the object store"):
        r.view(good.sha256, 0)
    assert len(cat.verify()) == 1 and "missing object" in cat.verify()[0]
    r.close(), cat.close()
    cat.close()                                            # idempotent
    with pytest.raises(CatalogError, match="closed"):
        cat.status()


# ---------------------------------------------------------------------------- integration
def test_pipeline_results_through_exr_and_reader(tmp_path):
    """Synth vehicle -> cameras -> render -> EXR artifact -> catalogue -> reader, with the
    generator's ground-truth part labels as the table."""
    pytest.importorskip("pyopencl")
    from ucad_catalog.exr import write_viewset_exr
    from ucad_cl.cameras import make_ring
    from ucad_cl.render import render_views
    from ucad_cl.synth import make_vehicle
    from ucad_cl.artifacts import MaterialPart, PartTable, Verdict

    car = make_vehicle(3)
    mesh = car.mesh()
    ring = make_ring(azimuth_step=120, size=20)
    views = render_views(mesh, ring)
    truth = car.truth["materials"]
    table = PartTable([MaterialPart(i, m.name, truth[m.name], 1.0, 1.0, 0, "truth", 1)
                       for i, m in enumerate(mesh.materials)])
    exr = write_viewset_exr(tmp_path / "v.exr", views, mesh)
    sha = _sha(f"synth-3:{mesh.sha256}".encode())
    entry = CatalogEntry.from_results(sha256=sha, path="synth/3.glb", size=1, mtime=0.0,
                                      verdict=Verdict(True), mesh=mesh, table=table, ring=ring,
                                      artifacts={"views.exr": exr})
    build(tmp_path / "cat", [entry]).close()
    with CatalogReader(tmp_path / "cat") as r:
        info = r.mesh(sha)
        assert (info.n_triangles, info.n_materials) == (mesh.n_faces, len(mesh.materials))
        assert np.array_equal(info.file_to_norm, mesh.file_to_norm)
        assert {p.name: p.part for p in r.parts(sha)} == truth
        assert r.parts(sha)[0].props["alpha_mode"] == mesh.materials[0].alpha_mode
        for v in range(ring.n_views):
            rec = r.view(sha, v)
            assert np.array_equal(rec.K, ring.K) and np.array_equal(rec.w2c, ring.w2c[v])
            assert rec.azimuth == ring.azimuth[v] and rec.elevation == ring.elevation[v]
            assert np.array_equal(rec.mat_id, views.mat_id[v])
            assert np.array_equal(rec.tri_id, views.tri_id[v])
            assert np.array_equal(rec.depth, views.depth[v])          # +inf background kept
            for part, mask in rec.part_masks.items():
                ids = [i + 1 for i, m in enumerate(mesh.materials) if truth[m.name] == part]
                assert np.array_equal(mask, np.isin(views.mat_id[v], ids))
            assert sum(m.sum() for m in rec.part_masks.values()) == (views.mat_id[v] > 0).sum()
