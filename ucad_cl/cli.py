"""``ucad-index``: the command-line entry point. Sub-commands live in ``ucad_cl/commands/``."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from . import __version__
from . import commands as _commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ucad-index",
        description="Turn vehicle CAD libraries into a part-labelled catalogue: ingest, filter, "
                    "render 360-degree material-index views with OpenCL, Canny edges, part "
                    "segmentation, material->part classification, pose features and search.",
        epilog="OpenCL device: --device P:D or a name substring (env UCAD_CL_DEVICE); "
               "default: the best PoCL CPU device that compiles (a named-CPU target, then the "
               "newer PoCL and LLVM). `ucad-index info` lists devices and says which and why.")
    parser.add_argument("--device", default=None,
                        help="OpenCL device: 'P:D' indices or a platform/device name substring")
    parser.add_argument("--version", action="store_true",
                        help="print version and the OpenCL device in use, then exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in sorted(m.name for m in pkgutil.iter_modules(_commands.__path__)):
        module = importlib.import_module(f"{_commands.__name__}.{mod}")
        if hasattr(module, "register"):           # helpers (common.py) have none
            module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    reader = _mesh_reader_ahead(argv)
    try:
        return _main(argv, reader)
    finally:
        if reader is not None:
            reader.close()                  # (done already where the fit's loader took it)


def _main(argv: list[str], mesh_reader) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    args.mesh_reader = mesh_reader
    # argparse cannot match an optional positional that follows options ("pose IMAGE --box ...
    # MESH"); a sub-command names such a positional with set_defaults(late_positional=NAME)
    late = getattr(args, "late_positional", None)
    if late and len(extra) == 1 and not extra[0].startswith("-") and getattr(args, late) is None:
        setattr(args, late, type(args.image)(extra[0]) if hasattr(args, "image") else extra[0])
        extra = []
    if extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if args.device:
        import os
        os.environ["UCAD_CL_DEVICE"] = args.device
    if args.version:
        print(f"ucad-index {__version__}")
        from .runtime import OpenCLUnavailable, get_runtime
        try:
            print(f"OpenCL device: {get_runtime().describe()}")
        except OpenCLUnavailable as exc:
            print(f"OpenCL device: none\n{exc}", file=sys.stderr)
            return 2
        return 0
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except RuntimeError as exc:
        from .runtime import OpenCLUnavailable
        if not isinstance(exc, OpenCLUnavailable):
            raise
        print(f"error: {exc}", file=sys.stderr)       # no usable OpenCL device: one line
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:          # output piped into `head` and the like
        import os
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def _mesh_reader_ahead(argv: list[str]):
    """For ``fit``: the mesh reader's child (``system.reader_child``), started before this
    process imports the parser's modules. Its imports (trimesh: ~0.5 s of a core) were the
    longest wait of a lone ``fit --mesh`` call: a child started after the parser left the fit
    waiting ~0.3 s for its mesh (docs/FIT.md). None for any other command, where the reader's
    modules are loaded already (a caller that loads meshes in process), or when no process can
    be started (the fit then starts its own)."""
    from .system import reader_child, reader_modules_loaded

    if _command_of(argv) != "fit" or reader_modules_loaded():
        return None
    try:
        return reader_child()
    except OSError:
        return None


def _command_of(argv: list[str]) -> str | None:
    """The sub-command ``argv`` names: its first word that is neither an option nor the value
    of the global ``--device``; None when there is none."""
    words = iter(argv)
    for word in words:
        if word == "--device":
            next(words, None)
        elif not word.startswith("-"):
            return word
    return None


if __name__ == "__main__":
    sys.exit(main())
