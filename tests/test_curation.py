"""Curators' label overrides (ucad_cl.curation): the file formats and their errors, the table
they give, and a build that applies them, records them, keeps them and re-processes only the
meshes whose fixes changed; ``show --low-confidence``."""
from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from ucad_cl.build import BuildOptions, build
from ucad_cl.curation import LabelOverrides, apply_label_overrides, mesh_options_hash

OPTS = dict(azimuth_step=45.0, elevations=(15.0,), size=96)
SHA = "ab" * 32


def test_text_and_json_files_read_the_same(tmp_path):
    (tmp_path / "fixes.txt").write_text(
        "# curated 2026-11-28\n\n"
        f"cars/a.glb \"Body Paint 2\" body\ncars/a.glb '#3' rim\n  {SHA} glass_01 window\n")
    (tmp_path / "fixes.json").write_text(json.dumps(
        {"cars/a.glb": {"Body Paint 2": "body", "#3": "rim"}, SHA: {"glass_01": "window"}},
        indent=1))
    a = LabelOverrides.read(tmp_path / "fixes.txt")
    b = LabelOverrides.read(tmp_path / "fixes.json")
    path = str((tmp_path / "cars" / "a.glb").resolve())
    assert a.as_items() == b.as_items() == (
        (path, "#3", "rim"), (path, "Body Paint 2", "body"), (SHA, "glass_01", "window"))
    # lookup: the path's fixes, the sha256's on top; any spelling of the path
    assert a.for_mesh(tmp_path / "cars" / ".." / "cars" / "a.glb", SHA) == {
        "#3": "rim", "Body Paint 2": "body", "glass_01": "window"}
    assert a.for_mesh(tmp_path / "b.glb", "cd" * 32) == {}
    assert LabelOverrides.from_items(a.as_items()).as_items() == a.as_items()
    # saved by an editor that writes a byte-order mark: the same fixes (the first line's key
    # once carried the mark, so its fixes never matched a mesh)
    for name in ("fixes.txt", "fixes.json"):
        bom = tmp_path / f"bom_{name}"
        bom.write_bytes(b"\xef\xbb\xbf" + (tmp_path / name).read_bytes())
        assert LabelOverrides.read(bom).as_items() == a.as_items(), name


@pytest.mark.parametrize("name,text,where,problem", [
    ("f.txt", "a.glb paint body\n\nb.glb paint rimm\n", ":3:", "unknown part 'rimm'"),
    ("f.txt", "a.glb Body Paint body\n", ":1:", "expected 'KEY MATERIAL PART'"),
    ("f.txt", "# x\na.glb \"Body paint body\n", ":2:", "No closing quotation"),
    ("f.json", '{"a.glb": {"paint": "body",}}', ":1:", "invalid JSON"),
    ("f.json", '{\n "a.glb": {\n  "paint": "body",\n  "glass": "windscreen"\n }\n}', ":4:",
     "unknown part 'windscreen' for material 'glass'"),
    ("f.json", '{\n "a.glb": "body"\n}', ":2:", "expected {material: part}"),
    ("f.json", '["a.glb"]', ":1:", "expected a JSON object"),
])
def test_errors_name_the_file_line_and_problem(tmp_path, name, text, where, problem):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ValueError) as exc:
        LabelOverrides.read(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}{where} ") and problem in msg and "\n" not in msg


def test_cli_bad_labels_file_is_one_line(tmp_path, capsys):
    from ucad_cl.cli import main
    bad = tmp_path / "fixes.txt"
    bad.write_text("a.glb paint bodywork\n")
    assert main(["build", str(tmp_path), "--catalog", str(tmp_path / "cat"),
                 "--labels-file", str(bad), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {bad}:1: unknown part 'bodywork'") and "\n" not in err
    assert not (tmp_path / "cat").exists()                 # refused before any work


def test_apply_by_name_and_index_records_what_was_decided():
    from ucad_cl.artifacts import MaterialPart, PartTable
    from ucad_cl.synth import make_vehicle
    mesh = make_vehicle(3, "sedan").mesh()
    names = [m.name for m in mesh.materials]
    rows = [MaterialPart(i, n, "body", 0.9, 0.8, 4, "vote", 100 + i, 0.6, None)
            for i, n in enumerate(names)]
    fixes = {names[1]: "plate", "#2": "interior", "nothing_here": "rim", f"#{len(names)}": "rim"}
    table, notes = apply_label_overrides(PartTable(rows), mesh, fixes)
    assert [r.part for r in table.rows] == ["body", "plate", "interior"] + ["body"] * (
        len(names) - 3)
    for i, r in enumerate(table.rows):
        if i in (1, 2):
            assert (r.decision, r.prob) == ("override", None)
            assert r.was == {"part": "body", "decision": "vote", "prob": 0.6}
            assert (r.score, r.view, r.pixels) == (0.9, 4, 100 + i)      # evidence kept
        else:
            assert r == rows[i]
    assert notes == [f"label override: no material '#{len(names)}', 'nothing_here' "
                     f"({len(names)} materials)"]
    assert mesh_options_hash("h" * 64, {}) == "h" * 64
    assert mesh_options_hash("h" * 64, {"#2": "rim"}) != mesh_options_hash("h" * 64,
                                                                            {"#2": "body"})


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    from ucad_cl.synth import write_library
    out = tmp_path_factory.mktemp("lib")
    write_library(out, 3, seed=23, messy_fraction=0.0, progress=False)
    return out


def _parts(cat) -> dict:
    from ucad_catalog.reader import CatalogReader
    with CatalogReader(cat) as r:
        return {Path(m.path).name: (m.sha256, m.detail, r.parts(m.sha256))
                for m in r.meshes(state=None)}


def _quiet(*a, **k):
    pass


def test_build_applies_records_keeps_and_reprocesses_only_changed(library, tmp_path, runtime,
                                                                   capsys):
    plain = _parts_of_build(library, tmp_path / "plain", BuildOptions(**OPTS))
    a, b, c = sorted(plain)
    sha_b = plain[b][0]
    name_a = plain[a][2][1].name
    wrong = "plate" if plain[a][2][1].part != "plate" else "rim"
    fixes = tmp_path / "fixes.txt"
    fixes.write_text(f"lib_link/{a} {shlex.quote(name_a)} {wrong}\n{sha_b} '#0' interior\n"
                     f"{sha_b} no_such_material rim\n")
    (tmp_path / "lib_link").symlink_to(library)          # a path key in another spelling
    cat = tmp_path / "cat"

    def run(labels_file):
        labels = LabelOverrides.read(labels_file) if labels_file else LabelOverrides()
        return build(library, cat, BuildOptions(**OPTS, label_overrides=labels.as_items()),
                     progress=False, log=_quiet)

    s = run(fixes)
    assert s.accepted == 3
    got = _parts(cat)
    for f in (a, b, c):
        for i, (p, q) in enumerate(zip(plain[f][2], got[f][2])):
            fixed = (f, i) in ((a, 1), (b, 0))
            assert q.part == ({(a, 1): wrong, (b, 0): "interior"}[(f, i)] if fixed else p.part)
            assert q.decision == ("override" if fixed else p.decision)
            if fixed:
                assert q.props["was"]["part"] == p.part and "prob" not in q.props
                assert q.props["was"]["prob"] == pytest.approx(p.props["prob"])
    assert "label override: no material 'no_such_material'" in got[b][1]
    # unchanged file: nothing re-processed
    s = run(fixes)
    assert (s.processed, s.skipped) == (0, 3)
    # one mesh's fix edited: that mesh alone re-processed, the others' fixes kept
    fixes.write_text(fixes.read_text().replace(f" {wrong}\n", " other\n"))
    s = run(fixes)
    assert (s.processed, s.skipped) == (1, 2)
    got = _parts(cat)
    assert got[a][2][1].part == "other" and got[b][2][0].part == "interior"
    # the file dropped: the two meshes that had fixes go back to the labeller's labels
    s = run(None)
    assert (s.processed, s.skipped) == (2, 1)
    assert _rows(_parts(cat)) == _rows(plain)

    # show --low-confidence: unseen first, then the labeller's probability; lines to paste
    from ucad_cl.cli import main
    capsys.readouterr()
    assert main(["show", sha_b[:12], "--catalog", str(cat), "--low-confidence", "4"]) == 0
    out = capsys.readouterr().out
    listed = out.split("labels-file line\n", 1)[1].strip().splitlines()
    rows = plain[b][2]
    conf = sorted(((0.0 if r.part == "unseen" else r.props["prob"]), -r.pixels, r.index)
                  for r in rows)[:4]
    assert len(listed) == 4
    for line, (cf, _, idx) in zip(listed, conf):
        r = rows[idx]
        part = "PART" if r.part == "unseen" else r.part      # a placeholder to edit
        assert line.split()[0] == f"{cf:.2f}" and line.split()[2] == r.part
        assert line.endswith(f"{sha_b} {shlex.quote(r.name)} {part}")
    # a listed line, its part edited, is a valid labels file
    pasted = tmp_path / "pasted.txt"
    pasted.write_text(listed[0][listed[0].index(sha_b):].rsplit(" ", 1)[0] + " interior\n")
    assert LabelOverrides.read(pasted).for_mesh(None, sha_b) == {rows[conf[0][2]].name:
                                                                  "interior"}


def _parts_of_build(library, cat, options) -> dict:
    build(library, cat, options, progress=False, log=_quiet)
    return _parts(cat)


def _rows(parts: dict) -> dict:
    return {f: [(r.index, r.name, r.part, r.decision, r.pixels, round(r.score, 6))
                for r in rows] for f, (_, _, rows) in parts.items()}
