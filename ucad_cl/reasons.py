"""Reason codes: the one list shared by ingest, filter, build, the engines, the generator and the
catalogue (``meshes.reason``). Its table in ``docs/CONVENTIONS.md`` is generated from ``CODES``
(``scripts/docs.py``; ``tests/test_docs.py`` checks).

Each code has a kind:

* ``rejection``: a verdict on the mesh (the file is at fault, or it fails the catalogue's
  criteria). Recorded with the mesh; final until the file or the options change, or until
  ``build --retry-failed`` names it. Codes marked ``retry`` are what ``--retry-failed`` with no
  code re-processes: the verdicts that may depend on the machine (time, memory) or on our code.
* ``environment``: the machine is at fault (disk full, I/O error, a worker killed from outside).
  Never recorded as a verdict on a mesh: the build stops with a message saying what to fix and a
  non-zero exit status, and the next run processes the meshes it did not finish.
* ``flag``: a note recorded on an accepted mesh (no rejection).

Other stages add codes by adding a row to ``CODES`` (keep it a plain table), then run
``.venv/bin/python scripts/docs.py``; CONTRIBUTING.md, 'A reason code', lists the rest.
"""
from __future__ import annotations

from typing import NamedTuple

REJECTION, ENVIRONMENT, FLAG = "rejection", "environment", "flag"
KINDS = (REJECTION, ENVIRONMENT, FLAG)


class Code(NamedTuple):
    kind: str
    retry: bool            # re-processed by ``build --retry-failed`` without arguments
    description: str


CODES: dict[str, Code] = {
    # -- rejections: the file is at fault (ingest)
    "unreadable": Code(REJECTION, False,
                       "the file cannot be parsed (bad magic, truncated, invalid JSON or "
                       "structure, a reader error) or cannot be read (permission, I/O error)"),
    "not_a_file": Code(REJECTION, False,
                       "the path is a FIFO, device, socket, directory, dangling symlink or "
                       "symlink loop, not a regular file (it is never opened)"),
    "unsafe_reference": Code(REJECTION, False,
                             "a file the model needs (glTF buffer) is referenced by an absolute "
                             "path or URL, leaves the model's folder, or is not a regular file"),
    "missing_reference": Code(REJECTION, False,
                              "a file the model needs (glTF buffer) does not exist"),
    "empty": Code(REJECTION, False,
                  "no triangles (an empty file, no faces, only degenerate faces) or zero extent"),
    "non_finite": Code(REJECTION, False,
                       "NaN/inf coordinates, or coordinates whose extent overflows float64"),
    "unsupported_compression": Code(REJECTION, False,
                                    "compressed geometry we cannot decode (meshopt; Draco "
                                    "without DracoPy)"),
    "unsupported_format": Code(REJECTION, False,
                               "an unknown file extension, or a feature the catalogue cannot "
                               "store (more than 65534 materials used)"),
    "too_large": Code(REJECTION, True,
                      "over a budget checked before allocation (file bytes, triangles, "
                      "vertices, materials, instances, buffer bytes, data: URI bytes, node "
                      "depth), or the mesh took more than the worker memory limit while it was "
                      "the only one in the worker"),
    "loader_crashed": Code(REJECTION, True,
                           "the worker process crashed (e.g. in a native library) on this mesh, "
                           "then again when it was retried alone without the data-segment "
                           "limit"),
    "timeout": Code(REJECTION, True,
                    "no progress on this mesh within --timeout, then again within twice that "
                    "with no other mesh in the worker"),
    "pipeline_error": Code(REJECTION, True,
                           "an unexpected error in ucad-cl's own code (a bug: please report "
                           "it); the build exits with status 1"),
    # -- rejections: the mesh fails the catalogue's criteria (filter)
    "too_many_triangles": Code(REJECTION, False,
                               "more triangles than --max-triangles (after decimation, if any)"),
    "too_few_materials": Code(REJECTION, False,
                              "fewer distinct materials than --min-materials"),
    "too_few_visible_parts": Code(REJECTION, False,
                                  "nothing visible, or fewer than --min-visible-materials "
                                  "materials with 20 or more visible pixels"),
    "dominant_material": Code(REJECTION, False,
                              "one material covers --dominant-fraction or more of the visible "
                              "pixels"),
    "uncertain_orientation": Code(REJECTION, False,
                                  "the estimated orientation has an up or front confidence under "
                                  "0.5 and --reject-uncertain-orientation was given (without it "
                                  "the mesh is accepted and counted as flagged in `status`)"),
    # -- environment: never a verdict on a mesh
    "disk_full": Code(ENVIRONMENT, False,
                      "no space left (ENOSPC, EDQUOT) writing the catalogue or its staging "
                      "folder"),
    "io_error": Code(ENVIRONMENT, False,
                     "an I/O error (EIO, EROFS, ...) on the catalogue's file system"),
    "worker_killed": Code(ENVIRONMENT, False,
                          "a worker was killed from outside (SIGKILL/SIGTERM, e.g. by the "
                          "kernel's OOM killer) three times while it held the same mesh"),
    "worker_lost": Code(ENVIRONMENT, False,
                        "Ray lost a task's worker or node (node died, object lost) twice"),
    "worker_start_failed": Code(ENVIRONMENT, False,
                                "a worker process could not start three times (OpenCL "
                                "unavailable, a memory limit too low to start)"),
}


def check(code: str, kind: str | None = None) -> str:
    """``code`` if it is registered (and of ``kind`` when given), else ValueError naming it."""
    entry = CODES.get(code)
    if entry is None:
        raise ValueError(f"unknown reason code {code!r} (see ucad_cl/reasons.py)")
    if kind is not None and entry.kind != kind:
        raise ValueError(f"reason code {code!r} is a {entry.kind} code, not a {kind} code")
    return code


def of_kind(kind: str) -> tuple[str, ...]:
    """Codes of one kind, in table order."""
    return tuple(c for c, e in CODES.items() if e.kind == kind)


def is_environment(code: str) -> bool:
    return CODES.get(code, Code(REJECTION, False, "")).kind == ENVIRONMENT


def default_retry() -> tuple[str, ...]:
    """The codes ``build --retry-failed`` re-processes when given no code."""
    return tuple(c for c, e in CODES.items() if e.retry)


def markdown_table() -> str:
    """The table of ``docs/CONVENTIONS.md`` (``scripts/docs.py`` writes it there)."""
    rows = ["| code | kind | retried by `--retry-failed` | meaning |", "|---|---|---|---|"]
    for code, e in CODES.items():
        rows.append(f"| `{code}` | {e.kind} | {'yes' if e.retry else ''} | {e.description} |")
    return "\n".join(rows)
