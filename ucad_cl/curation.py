"""Curators' label corrections: a per-mesh override file (material -> part) that ``build``
applies after classification (``--labels-file F``), so a person can fix the few labels that
matter and keep the fixes through every rebuild.

``apply_label_overrides(table, mesh, fixes)`` -> (PartTable, notes): each material a fix names
takes the fix's part with decision ``'override'``; its row keeps the evidence (score, iou, view,
pixels) and records what the classifier had decided in ``was`` (part, decision, prob); ``prob``
becomes None (a person decided, not the labeller). A fix naming no material of the mesh is a
note (kept in the catalogue's detail), never an error: the file may outlive a model's edits.

File format (``LabelOverrides.read``), like the orientation override file
(``orient.OrientationOverrides``): the mesh KEY is its sha256 (as ``ucad-index show`` prints
it) or its path (absolute, or relative to the override file); MATERIAL is the material's name
as the file spells it, or ``#N``, the material index N (0-based, the order ``show`` lists;
a name of ``#`` and digits is read as an index); PART is one of ``PART_NAMES``.

* JSON (``.json``): ``{"KEY": {"MATERIAL": "PART", ...}, ...}``.
* Text (any other suffix): lines ``KEY MATERIAL PART``, split as a shell splits words, so
  names with spaces are quoted (``car.glb "Body Paint 2" body``); blank lines and lines whose
  first character other than blanks is ``#`` are ignored.

Lookup (``for_mesh``): the path's fixes, then the sha256's (a sha256 entry wins for the same
material). A name shared by several materials fixes all of them; an index fix wins over a name
fix for the same material. Errors name the file, the line and the problem (ValueError).

Rebuilds: the fixes of a mesh enter that mesh's options hash (``mesh_options_hash``), not the
run's, so editing the file re-processes exactly the meshes whose fixes changed (added,
edited or removed) and skips the others; a mesh with no fix keeps the run's hash.
"""
from __future__ import annotations

import hashlib
import json
import os
import shlex
from dataclasses import replace
from pathlib import Path
from typing import Mapping

from .artifacts import PART_NAMES, Mesh, PartTable

DECISION = "override"


def apply_label_overrides(table: PartTable, mesh: Mesh,
                          fixes: Mapping[str, str]) -> tuple[PartTable, list[str]]:
    """The table with ``fixes`` ({material name or '#N': part}) applied, and notes naming the
    fixes that match no material of ``mesh`` (sorted). Rows keep material index order."""
    by_index: dict[int, str] = {}
    missing = []
    names = [m.name for m in mesh.materials]
    for key, part in sorted(fixes.items(), key=lambda kv: _is_index(kv[0])):  # names first
        if _is_index(key):
            i = int(key[1:])
            hit = [i] if i < len(names) else []
        else:
            hit = [i for i, n in enumerate(names) if n == key]
        if not hit:
            missing.append(key)
        for i in hit:
            by_index[i] = part
    rows = []
    for r in table.rows:
        part = by_index.get(r.material)
        if part is None:
            rows.append(r)
            continue
        was = {"part": r.part, "decision": r.decision, "prob": r.prob}
        rows.append(replace(r, part=part, decision=DECISION, prob=None, was=was))
    notes = ([f"label override: no material {', '.join(repr(k) for k in sorted(missing))} "
              f"({len(names)} materials)"] if missing else [])
    return PartTable(rows=rows), notes


def mesh_options_hash(run_hash: str, fixes: Mapping[str, str]) -> str:
    """The options hash a mesh is recorded with: the run's when it has no fix, else the sha256
    of the run's hash and its fixes (canonical JSON)."""
    if not fixes:
        return run_hash
    blob = json.dumps([run_hash, sorted(fixes.items())], separators=(",", ":"))
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


class LabelOverrides:
    """``{mesh key: {material: part}}`` (see the module docstring); keys are sha256 digests or
    resolved absolute paths."""

    def __init__(self, entries: Mapping[str, Mapping[str, str]] | None = None):
        self.entries: dict[str, dict[str, str]] = {}
        for key, fixes in (entries or {}).items():
            for material, part in fixes.items():
                self.entries.setdefault(str(key), {})[str(material)] = check_part(part)

    @classmethod
    def from_items(cls, items) -> "LabelOverrides":
        """From ``as_items()``'s ``(key, material, part)`` triples (what ``BuildOptions``
        carries to the workers)."""
        out = cls()
        for key, material, part in items:
            out.entries.setdefault(str(key), {})[str(material)] = check_part(part)
        return out

    def as_items(self) -> tuple[tuple[str, str, str], ...]:
        """Sorted ``(key, material, part)`` triples."""
        return tuple(sorted((k, m, p) for k, fixes in self.entries.items()
                            for m, p in fixes.items()))

    def for_mesh(self, path: str | os.PathLike | None, sha256: str) -> dict[str, str]:
        """The fixes of one mesh: its resolved path's (if a path is given), then its sha256's
        on top ({} if none)."""
        if not self.entries:
            return {}
        out = dict(self.entries.get(str(Path(path).resolve()), {})) if path else {}
        out.update(self.entries.get(sha256, {}))
        return out

    @classmethod
    def read(cls, path: str | os.PathLike) -> "LabelOverrides":
        """Parse an override file (JSON or text lines); ValueError names file, line, problem."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8-sig")    # an editor's BOM dropped
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{p}: cannot read label overrides: {exc}") from None
        triples = _json_triples(p, text) if p.suffix.lower() == ".json" else _text_triples(p, text)
        out = cls()
        for line, key, material, part in triples:
            where = f"{p}:{line}" if line else str(p)
            if part not in PART_NAMES:
                raise ValueError(f"{where}: unknown part {part!r} for material {material!r} "
                                 f"(parts: {', '.join(PART_NAMES)})")
            if not material:
                raise ValueError(f"{where}: empty material name for mesh {key!r}")
            if not _is_sha256(key):
                kp = Path(key)
                key = str((kp if kp.is_absolute() else p.parent / kp).resolve())
            out.entries.setdefault(key, {})[material] = part
        return out


def check_part(part) -> str:
    """``part`` if it is one of ``PART_NAMES``; ValueError otherwise."""
    if part not in PART_NAMES:
        raise ValueError(f"unknown part {part!r} (parts: {', '.join(PART_NAMES)})")
    return str(part)


def _text_triples(p: Path, text: str) -> list[tuple[int, str, str, str]]:
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            words = shlex.split(line, comments=False, posix=True)
        except ValueError as exc:
            raise ValueError(f"{p}:{n}: {exc} in {line.strip()!r}") from None
        if len(words) != 3:
            raise ValueError(f"{p}:{n}: expected 'KEY MATERIAL PART' (e.g. 'car.glb "
                             f"\"Body Paint\" body'; quote names with spaces), got "
                             f"{line.strip()!r}")
        out.append((n, words[0], words[1], words[2]))
    return out


def _json_triples(p: Path, text: str) -> list[tuple[int, str, str, str]]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}:{exc.lineno}: invalid JSON: {exc.msg}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{p}:1: expected a JSON object {{path or sha256: {{material: part}}}}")
    lines = text.splitlines()
    out = []
    for key, fixes in data.items():
        line = _line_of(lines, key, 0)
        if not isinstance(fixes, dict):
            raise ValueError(f"{p}:{line}: entry {key!r}: expected {{material: part}}, got "
                             f"{type(fixes).__name__}")
        for material, part in fixes.items():
            at = _line_of(lines, material, max(line - 1, 0)) or line
            if not isinstance(part, str):
                raise ValueError(f"{p}:{at}: material {material!r}: the part must be a string, "
                                 f"got {type(part).__name__}")
            out.append((at, key, material, part))
    return out


def _line_of(lines: list[str], key: str, start: int) -> int:
    """1-based line of the first ``"key"`` at or after line index ``start`` (0 if not found:
    e.g. a key written with escapes)."""
    quoted = json.dumps(key)
    for i in range(start, len(lines)):
        if quoted in lines[i]:
            return i + 1
    return 0


def _is_index(key: str) -> bool:
    return len(key) > 1 and key[0] == "#" and key[1:].isdigit()


def _is_sha256(text: str) -> bool:
    return len(text) == 64 and all(c in "0123456789abcdef" for c in text)
