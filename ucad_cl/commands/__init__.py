"""CLI sub-commands: every module here with a ``register(subparsers)`` is one; cli.py loads them
all (``common.py`` holds helpers they share).

A sub-command module adds its parser with ``subparsers.add_parser(NAME, help=..., description=...)``
and sets ``func=`` to a callable taking the parsed ``argparse.Namespace`` and returning an exit
status (0 success, 1 some inputs failed, 2 usage or environment error).
"""
