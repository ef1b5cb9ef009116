"""Regenerate the documented tables whose source is code, or check them (``--check``).

* docs/CONVENTIONS.md, section 'Reason codes': the table is ``ucad_cl.reasons.markdown_table()``
  (edit ``CODES`` in ucad_cl/reasons.py, never the table).

Usage: ``.venv/bin/python scripts/docs.py`` (rewrite) or ``... --check`` (exit 1 naming each
stale file). ``tests/test_docs.py`` runs the check.
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONVENTIONS = ROOT / "docs" / "CONVENTIONS.md"
HEADER = "| code | kind |"


def with_reason_table(text: str) -> str:
    """``text`` (CONVENTIONS.md) with its reason-code table replaced by the registry's."""
    from ucad_cl.reasons import markdown_table

    lines = text.split("\n")
    start = next((i for i, line in enumerate(lines) if line.startswith(HEADER)), None)
    if start is None:
        raise ValueError(f"{CONVENTIONS}: no reason-code table (a line starting {HEADER!r})")
    end = start
    while end < len(lines) and lines[end].startswith("|"):
        end += 1
    return "\n".join(lines[:start] + markdown_table().split("\n") + lines[end:])


def main(argv: list[str]) -> int:
    check = argv == ["--check"]
    if argv and not check:
        print("usage: scripts/docs.py [--check]", file=sys.stderr)
        return 2
    stale = []
    for path, render in ((CONVENTIONS, with_reason_table),):
        text = path.read_text(encoding="utf-8")
        new = render(text)
        if new != text:
            stale.append(path)
            if not check:
                path.write_text(new, encoding="utf-8")
                print(f"rewrote {path.relative_to(ROOT)}")
    if check and stale:
        print("stale: " + ", ".join(str(p.relative_to(ROOT)) for p in stale)
              + " (run .venv/bin/python scripts/docs.py)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
