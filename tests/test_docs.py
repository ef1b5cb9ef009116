"""Documented tables equal their one source in the code, checked in one place. Each failure
names the command or the file that fixes it.

* docs/CONVENTIONS.md's reason-code table is generated from ``ucad_cl/reasons.py``
  (``scripts/docs.py``); every code the code emits is registered; ``filter.py``'s docstring names
  exactly the codes the filter emits.
* ucad_catalog/SCHEMA.md lists exactly the SQL columns, artifact kinds and export columns.
* Every relative link in the README, CONTRIBUTING.md and docs/ points at a file that exists.
"""
from __future__ import annotations

import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from ucad_cl import reasons

ROOT = Path(__file__).resolve().parents[1]
REGENERATE = ".venv/bin/python scripts/docs.py"


def test_reason_table_generated_from_the_registry():
    conventions = (ROOT / "docs" / "CONVENTIONS.md").read_text(encoding="utf-8")
    assert reasons.markdown_table() in conventions, (
        f"docs/CONVENTIONS.md's reason-code table differs from ucad_cl/reasons.py: run "
        f"`{REGENERATE}` (edit the registry, never the table)")
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "docs.py"), "--check"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr


def emitted_codes(text: str) -> set[str]:
    """Reason codes a source file emits, by the spellings the code uses."""
    used: set[str] = set()
    for pattern in (r'Verdict\(False, "(\w+)"', r'Verdict\(\s*False,\s*"(\w+)"',
                    r'IngestError\([^,]+, "(\w+)"', r'\brecord\(i, "(\w+)"',
                    r'rejected_entry\(ref, [\w.()]+, "(\w+)"', r'BuildStopped\("(\w+)"'):
        used |= set(re.findall(pattern, text))
    return used


def test_every_emitted_reason_code_is_registered():
    from ucad_cl.synth import REJECT_OF

    for code in REJECT_OF.values():
        assert reasons.CODES[code].kind == reasons.REJECTION, code
    used: set[str] = set()
    for src in (ROOT / "ucad_cl").rglob("*.py"):
        used |= emitted_codes(src.read_text(encoding="utf-8"))
    unknown = used - set(reasons.CODES)
    assert len(used) >= 15 and not unknown, (
        f"codes emitted but not in ucad_cl/reasons.py: {sorted(unknown)}: add a row to CODES, "
        f"then run `{REGENERATE}`")
    with pytest.raises(ValueError, match="unknown reason code"):
        reasons.check("bogus")


def test_filter_docstring_names_the_filter_codes():
    """The filter's docstring lists, in check order, exactly the codes it emits."""
    import ucad_cl.filter as filter_module

    text = Path(filter_module.__file__).read_text(encoding="utf-8")
    documented = set(re.findall(r"^\* ``(\w+)``", filter_module.__doc__ or "", re.M))
    emitted = emitted_codes(text)
    assert documented == emitted, (
        f"ucad_cl/filter.py: its docstring's list of checks names {sorted(documented)}, the "
        f"code emits {sorted(emitted)}: add the missing bullet (or remove the stale one)")
    assert all(reasons.CODES[c].kind == reasons.REJECTION for c in emitted)


def doc_tables(text: str) -> dict[str, list[list[str]]]:
    """{heading: rows of the first markdown table after it} for '###' headings and the
    'Meshes table' / 'Materials table' paragraphs of SCHEMA.md."""
    out: dict[str, list[list[str]]] = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"### `?([\w ]+?)`?(?: \(|$)", line)
        if m or line.startswith(("Meshes table", "Materials table")):
            current = m.group(1) if m else "export " + line.split(" table")[0].lower()
            continue
        if line.startswith("#"):                 # another heading ends the table's section
            current = None
            continue
        if current and line.startswith("|") and not line.startswith("|---"):
            cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
            if cells[0] not in ("column", "kind", "key"):
                out.setdefault(current, []).append(cells)
    return out


def test_schema_doc_matches_the_code(tmp_path):
    """SCHEMA.md lists exactly the SQL columns (names and types), the artifact kinds and the
    export columns the code defines: the two cannot drift apart."""
    from ucad_catalog import Catalog
    from ucad_catalog._db import ARTIFACT_KINDS, SCHEMA_VERSION
    from ucad_catalog.export import MATERIAL_COLUMNS, MESH_COLUMNS

    text = (ROOT / "ucad_catalog" / "SCHEMA.md").read_text(encoding="utf-8")
    assert text.startswith(f"# Catalogue format — `schema_version` {SCHEMA_VERSION}")
    doc = doc_tables(text)
    Catalog.open(tmp_path / "c").close()
    con = sqlite3.connect(tmp_path / "c" / "catalog.sqlite")
    for table in ("runs", "meshes", "materials", "views", "artifacts"):
        actual = {r[1]: r[2] for r in con.execute(f"PRAGMA table_info({table})")}
        documented = {c[0].strip("`"): c[1] for c in doc[table]}
        assert documented == actual, f"ucad_catalog/SCHEMA.md, table {table}"
    con.close()
    assert {c[0].strip("`"): c[1] for c in doc["Artifact kinds"]} == ARTIFACT_KINDS
    for name, columns in (("export meshes", MESH_COLUMNS),
                          ("export materials", MATERIAL_COLUMNS)):
        assert [(c[0].strip("`"), c[1], c[2]) for c in doc[name]] == list(columns), name


def test_relative_links_resolve():
    pages = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", ROOT / "ucad_catalog" / "SCHEMA.md",
             *sorted((ROOT / "docs").glob("*.md"))]
    broken = []
    for page in pages:
        if not page.exists():
            continue
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            if not (page.parent / target.split("#")[0]).exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert broken == []


def test_readme_stays_short():
    """The README is the two-minute page (CONTRIBUTING.md, 'Documentation'): details go in
    docs/ and the README links them."""
    n = len((ROOT / "README.md").read_text(encoding="utf-8").splitlines())
    assert n <= 150, f"README.md has {n} lines (at most 150): move details into docs/"
