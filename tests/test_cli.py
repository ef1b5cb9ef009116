"""The command line on a catalogue made by the ``Catalog`` store: no OpenCL, no mesh built.

* Every command has a ``--help`` that builds without OpenCL; every command with ``--json``
  documents its shape in ucad_catalog/SCHEMA.md, 'Command output' (``<command> output``).
* Each machine-readable output (``status --json``, ``verify --json``, ``export``, the parts JSON,
  ``pose --json``) carries exactly the documented keys, with values checked against raw SQL.
* ``status`` text and JSON come from one ``CatalogReader.status()`` snapshot; a reader's
  ``snapshot()`` holds status and runs together while a writer commits.
* Readers never take the writer lock; errors are one line.

A new command slots in by documenting its ``--json`` keys in SCHEMA.md and adding a test here
that reads them with ``documented_keys``.
"""
from __future__ import annotations

import argparse
import gzip
import hashlib
import io
import json
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.test_docs import doc_tables
from ucad_catalog import Catalog, CatalogReader
from ucad_catalog.entry import CatalogEntry, MaterialRow, ViewRow
from ucad_cl.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "ucad_catalog" / "SCHEMA.md"


def documented_keys(table: str) -> list[str]:
    """Keys of one 'Command output' table of SCHEMA.md (e.g. 'status output')."""
    rows = doc_tables(SCHEMA.read_text(encoding="utf-8"))[table]
    return [r[0].strip("`") for r in rows]


def _entry(i: int, library: Path, *, state: str = "accepted", reason: str = "",
           uncertain: bool = False) -> CatalogEntry:
    rng = np.random.default_rng(i)
    sha = hashlib.sha256(f"cli-mesh-{i}".encode()).hexdigest()
    e = CatalogEntry(sha256=sha, path=f"cars/car_{i}.glb", size=100 + i, mtime=1.7e9 + i,
                     state=state, reason=reason, detail=f"detail {i}" if reason else "",
                     n_triangles=1000 + i, n_materials=2, library_root=str(library),
                     orientation={"rotation": np.eye(3).tolist(), "up_confidence": 0.9,
                                  "front_confidence": 0.3 if uncertain else 0.9,
                                  "source": "auto", "cues": {"wheels": 0.5},
                                  "flags": ["front_ambiguous"] if uncertain else [],
                                  "symmetry": 0.9, "mirror_z": 0.0, "uncertain": uncertain})
    if state == "accepted":
        e.materials = [MaterialRow(m, f"mat_{m}", ("body", "window")[m], 0.9, 0.8, 0,
                                   "best-view", 50) for m in range(2)]
        e.views = [ViewRow(v, 90.0 * v, 15.0, np.eye(3), np.eye(4)) for v in range(4)]
        buf = io.BytesIO()
        np.save(buf, rng.standard_normal((4, 8)).astype(np.float32))
        e.artifacts = {"features.npy": buf.getvalue(),
                       "edges.npy.gz": gzip.compress(b"edges %d" % i, mtime=0)}
    return e


@pytest.fixture()
def catalogue(tmp_path) -> tuple[Path, Path]:
    """(library folder, catalogue): 3 accepted meshes (one flagged uncertain), 2 rejected, and
    three runs: a finished one, a stopped one, and a second finished one."""
    library, cat = tmp_path / "lib", tmp_path / "cat"
    with Catalog.open(cat) as c:
        run = c.begin_run({"size": 8}, "local")
        for i, kw in enumerate([{}, {"uncertain": True}, {},
                                {"state": "rejected", "reason": "too_few_materials"},
                                {"state": "rejected", "reason": "unreadable"}]):
            c.commit_mesh(_entry(i, library, **kw))
        c.finish_run(run, {"skipped": 0, "failed": 0})
        run = c.begin_run({"size": 8}, "local")
        c.finish_run(run, {"skipped": 5, "stopped": "disk_full"})
        run = c.begin_run({"size": 16}, "ray")
        c.commit_mesh(_entry(5, library, state="rejected", reason="too_few_materials"))
        c.finish_run(run, {"skipped": 5})
    return library, cat


def _sql(cat: Path, query: str) -> list[tuple]:
    con = sqlite3.connect(cat / "catalog.sqlite")
    try:
        return con.execute(query).fetchall()
    finally:
        con.close()


def _json(capsys, argv: list[str], status: int = 0):
    capsys.readouterr()
    assert main(argv) == status
    return json.loads(capsys.readouterr().out)


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in build_parser()._actions
                  if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


# ---------------------------------------------------------------------------- every command
def test_every_command_has_help_without_opencl():
    """`ucad-index CMD --help` for every command, in a fresh interpreter that never loads
    pyopencl, onnxruntime or trimesh."""
    names = sorted(_subparsers())
    assert {"build", "status", "show", "export", "verify", "gc", "pose"} <= set(names)
    code = ("import sys, contextlib, io\nfrom ucad_cl.cli import main\n"
            f"for name in {names!r}:\n"
            "    out = io.StringIO()\n"
            "    with contextlib.redirect_stdout(out):\n"
            "        try:\n            main([name, '--help'])\n"
            "        except SystemExit as e:\n            assert e.code == 0, name\n"
            "    assert out.getvalue().startswith('usage: ucad-index ' + name), name\n"
            "heavy = [m for m in ('pyopencl', 'onnxruntime', 'trimesh') if m in sys.modules]\n"
            "assert not heavy, heavy\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-2000:]


def test_every_json_output_is_documented():
    """A command with --json has a '<command> output' table in SCHEMA.md, 'Command output'."""
    tables = doc_tables(SCHEMA.read_text(encoding="utf-8"))
    with_json = sorted(name for name, p in _subparsers().items()
                       if any("--json" in a.option_strings for a in p._actions))
    missing = [n for n in with_json if f"{n} output" not in tables]
    assert with_json and not missing, (
        f"document the --json keys of {missing} in ucad_catalog/SCHEMA.md, 'Command output' "
        f"(a '### NAME output' table) and pin them in tests/test_cli.py")


# ---------------------------------------------------------------------------- status
def test_status_json_shape_and_values(catalogue, capsys):
    _, cat = catalogue
    st = _json(capsys, ["status", "--catalog", str(cat), "--json"])
    assert list(st) == documented_keys("status output")
    assert st["root"] == str(cat.resolve()) or Path(st["root"]).resolve() == cat.resolve()
    by_state = dict(_sql(cat, "SELECT state, count(*) FROM meshes GROUP BY state"))
    assert st["by_state"] == by_state == {"accepted": 3, "rejected": 3}
    assert st["meshes"] == 6
    assert st["by_reason"] == {"too_few_materials": 2, "unreadable": 1}
    assert list(st["by_reason"]) == sorted(st["by_reason"])
    assert st["flagged"] == {"uncertain_orientation": 1}
    objects = _sql(cat, "SELECT count(DISTINCT sha256), sum(bytes) FROM (SELECT DISTINCT "
                        "sha256, bytes FROM artifacts)")[0]
    assert (st["objects"], st["object_bytes"]) == objects and objects[0] == 6
    assert st["n_runs"] == 3
    runs = st["runs"]
    assert isinstance(runs, list) and [r["id"] for r in runs] == [3, 2, 1]     # newest first
    assert st["last_run"] == runs[0]
    for r in runs:
        assert list(r) == documented_keys("run object")
    raw = {r[0]: r for r in _sql(cat, "SELECT id, engine, options_hash, counts FROM runs")}
    for r in runs:
        assert (r["engine"], r["options_hash"], r["counts"]) == (
            raw[r["id"]][1], raw[r["id"]][2], json.loads(raw[r["id"]][3]))
    assert runs[1]["counts"]["stopped"] == "disk_full"
    assert runs[0]["counts"] == {"accepted": 0, "rejected": 1, "skipped": 5}
    with CatalogReader(cat) as reader:
        assert reader.runs(5) == runs                    # the same rows as the reader's
        assert reader.status(recent=1)["runs"] == runs[:1]


def test_status_text_and_json_agree(catalogue, capsys):
    _, cat = catalogue
    st = _json(capsys, ["status", "--catalog", str(cat), "--json"])
    assert main(["status", "--catalog", str(cat)]) == 0
    out = capsys.readouterr().out
    assert f"meshes: {st['meshes']}  accepted: 3  rejected: 3" in out
    for reason, n in st["by_reason"].items():
        assert f"rejected {reason:<24} {n}" in out
    assert "flagged  uncertain_orientation    1" in out
    assert f"  search index: {st['search_index']}" in out
    rows = out.split("recent runs:\n", 1)[1].splitlines()[1:]
    assert [int(r.split()[0]) for r in rows] == [r["id"] for r in st["runs"]]
    assert "stopped: disk_full" in rows[1] and rows[0].split()[3] == "ray"


def test_status_help_says_how_many_runs(capsys):
    with pytest.raises(SystemExit):
        main(["status", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "the last 5 runs" in out and "SCHEMA.md" in out


def test_status_and_runs_in_one_snapshot_while_a_writer_commits(catalogue):
    """Inside ``snapshot()`` status and runs read one state (this raised 'cannot start a
    transaction within a transaction' before), even when a writer commits in between."""
    library, cat = catalogue
    with CatalogReader(cat) as reader, reader.snapshot():
        before = reader.status()
        with Catalog.open(cat, create=False) as writer:
            run = writer.begin_run({"size": 8}, "local")
            writer.commit_mesh(_entry(9, library))
            writer.finish_run(run)
        assert reader.status() == before and reader.runs(5) == before["runs"]
        assert reader.status()["meshes"] == 6 and reader.runs(1)[0]["id"] == 3
    with CatalogReader(cat) as reader:
        after = reader.status()
        assert after["meshes"] == 7 and after["runs"][0]["id"] == 4
    with Catalog.open(cat, create=False) as writer:             # the writer's own view
        assert writer.status()["n_runs"] == 4


# ---------------------------------------------------------------------------- verify
def test_verify_json_shape_problems_and_exit_status(catalogue, capsys):
    _, cat = catalogue
    report = _json(capsys, ["verify", "--catalog", str(cat), "--json"])
    assert list(report) == documented_keys("verify output")
    assert report["problems"] == [] and report["unreferenced"] == [] == report["tmp_files"]
    assert report["objects"] == 6
    assert report["bytes"] == _sql(cat, "SELECT sum(bytes) FROM (SELECT DISTINCT sha256, bytes "
                                        "FROM artifacts)")[0][0]
    (sha,) = _sql(cat, "SELECT sha256 FROM artifacts WHERE kind='features.npy' LIMIT 1")[0]
    victim = next(p for p in (cat / "objects").rglob("*") if p.is_file() and sha in p.name)
    victim.write_bytes(b"corrupt")
    stray = victim.parent / ("0" * 64)
    stray.write_bytes(b"nobody")
    report = _json(capsys, ["verify", "--catalog", str(cat), "--json"], status=1)
    assert len(report["problems"]) == 1 and sha in report["problems"][0]
    assert [list(u) for u in report["unreferenced"]] == [[str(stray.relative_to(cat / "objects")),
                                                          6]]


# ---------------------------------------------------------------------------- export, parts
def test_export_jsonl_rows_have_the_documented_columns(catalogue, tmp_path, capsys):
    from ucad_catalog.export import MATERIAL_COLUMNS, MESH_COLUMNS

    _, cat = catalogue
    out = tmp_path / "x.jsonl"
    assert main(["export", "--catalog", str(cat), "--out", str(out)]) == 0
    assert capsys.readouterr().out == (f"exported 6 meshes to {out} and their materials to "
                                       f"{tmp_path / 'x.materials.jsonl'}\n")
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == 6 and all(set(r) == {c[0] for c in MESH_COLUMNS} for r in rows)
    mats = [json.loads(line) for line in (tmp_path / "x.materials.jsonl").read_text()
            .splitlines()]
    assert len(mats) == 6 and all(set(m) == {c[0] for c in MATERIAL_COLUMNS} for m in mats)
    meta = json.loads((tmp_path / "x.jsonl.meta.json").read_text())
    assert meta["ucad:export_version"] == "1"


def test_parts_json_and_csv_have_the_documented_columns(tmp_path):
    import csv
    from dataclasses import fields

    from ucad_cl.artifacts import MaterialPart, PartTable
    from ucad_cl.commands.parts import COLUMNS, write_table

    table = PartTable([MaterialPart(0, "paint", "body", 0.9, 0.8, 3, "best-view", 120, 0.97,
                                    None),
                       MaterialPart(1, "glass", "window", 0.5, 0.4, 1, "split", 60, None,
                                    [["window", [0]], ["light", [1]]])])
    write_table(table, tmp_path / "car")
    rows = json.loads((tmp_path / "car.parts.json").read_text())
    keys = documented_keys("parts output")
    assert keys == list(COLUMNS) == [f.name for f in fields(MaterialPart)]
    assert [list(r) for r in rows] == [keys, keys]
    assert rows[1]["split"] == [["window", [0]], ["light", [1]]] and rows[1]["prob"] is None
    with open(tmp_path / "car.parts.csv", newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        assert reader.fieldnames == keys
        assert json.loads(list(reader)[1]["split"]) == rows[1]["split"]


def test_pose_json_has_the_documented_keys():
    """The JSON of ``pose --json`` (single mesh) from a hand-made estimate; the search itself
    is tested with OpenCL in tests/test_pose.py and tests/test_build.py."""
    from ucad_cl.commands.pose import estimate_json
    from ucad_cl.foreground import ObjectMask
    from ucad_cl.pose import PoseCandidate, PoseEstimate

    best = PoseCandidate(30.0, 15.0, 2.5, 0.1, 3, refined=True, cues={"hog": 0.1},
                         K=np.eye(3), w2c=np.eye(4))
    twin = PoseCandidate(-30.0, 15.0, 2.5, 0.12, 9, flipped=True, twin="mirror", gap=0.02)
    est = PoseEstimate([best, twin], ObjectMask(np.ones((4, 4), bool), "mask", (0, 0, 4, 4)),
                       ambiguous=True)
    doc = json.loads(json.dumps(estimate_json(est, "p.jpg", "m.glb", "p_pose.png")))
    assert list(doc) == documented_keys("pose output")
    assert list(doc["object"]) == ["source", "box", "kept", "pixels"]
    assert [list(c) for c in doc["candidates"]] == [
        ["rank", "azimuth", "elevation", "distance", "score", "gap", "refined", "flipped",
         "twin", "view", "cues", "K", "w2c"]] * 2
    assert doc["candidates"][1]["K"] is None and doc["candidates"][0]["w2c"] == np.eye(4).tolist()


# ---------------------------------------------------------------------------- show, errors
def test_show_by_id_path_and_name_and_export_errors(catalogue, tmp_path, capsys):
    library, cat = catalogue
    assert main(["export", "--catalog", str(cat), "--out", "/missing/dir/x.jsonl"]) == 2
    assert capsys.readouterr().err == ("error: cannot write /missing/dir/x.jsonl: folder "
                                       "/missing/dir does not exist\n")
    assert main(["export", "--catalog", str(cat), "--out", str(tmp_path / "x.txt")]) == 2
    assert "cannot tell the export format" in capsys.readouterr().err
    pq = pytest.importorskip("pyarrow.parquet")
    assert main(["export", "--catalog", str(cat), "--out", str(tmp_path / "x.parquet")]) == 0
    assert pq.read_table(tmp_path / "x.parquet").num_rows == 6           # suffix -> Parquet
    assert pq.read_table(tmp_path / "x.materials.parquet").num_rows == 6
    assert main(["export", "--catalog", str(cat), "--out", str(tmp_path / "y.parquet"),
                 "--format", "jsonl"]) == 0                              # --format overrides
    assert (tmp_path / "y.parquet").read_text().startswith('{"artifacts":')
    capsys.readouterr()
    with CatalogReader(cat) as r:
        m = r.meshes()[0]
    for key in (m.sha256[:8], str(library / m.path), m.name):
        assert main(["show", key, "--catalog", str(cat)]) == 0
        out = capsys.readouterr().out
        assert out.startswith(f"mesh {m.sha256[:12]}  {m.path}")
        assert "features.npy" in out and "mat_1" in out
    assert main(["show", "nothing-like-it", "--catalog", str(cat)]) == 2
    assert "0 meshes match 'nothing-like-it'" in capsys.readouterr().err
    assert main(["show", "car_", "--catalog", str(cat)]) == 2
    assert capsys.readouterr().err.startswith("error: 0 meshes match")
    assert main(["status", "--catalog", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_readers_work_while_a_writer_holds_the_lock(catalogue, tmp_path, capsys):
    """status, export, show and verify never take the writer lock; gc does, and says so in
    one line."""
    _, cat = catalogue
    with Catalog.open(cat, create=False):             # a build in progress holds this lock
        assert main(["status", "--catalog", str(cat)]) == 0
        assert "accepted: 3" in capsys.readouterr().out
        assert main(["export", "--catalog", str(cat), "--out", str(tmp_path / "x.jsonl")]) == 0
        assert len((tmp_path / "x.jsonl").read_text().splitlines()) == 6
        assert main(["show", "car_0.glb", "--catalog", str(cat)]) == 0
        assert main(["verify", "--catalog", str(cat)]) == 0
        capsys.readouterr()
        assert main(["gc", "--catalog", str(cat)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "open for writing by another process" in err[0], err
