"""The ``slamlens`` program: ``slamlens COMMAND [flags]`` runs one command of
:data:`~slamlens.services.commands.registry.COMMANDS` (docs/cli.md).

A command's parser is its settings' flags (:func:`slamlens.common.config.add_flags`: every
field a TOML key of ``--config FILE`` and a flag) and the common flags; docs/cli.md is
generated from the same parsers (``python -m slamlens.services.commands.reference``).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from slamlens.common.cli import add_common_flags, run_cli
from slamlens.common.config import add_flags
from slamlens.common.memory import keep_freed_memory
from slamlens.services.commands.registry import COMMANDS, import_service_module


def command_parser(name: str) -> argparse.ArgumentParser:
    """The parser of ``slamlens NAME``: its settings' flags, then the common flags."""
    command = COMMANDS[name]
    parser = argparse.ArgumentParser(prog=f"slamlens {name}", description=command.help)
    groups: dict[str, Any] = {}
    cls = command.settings_class()
    if cls is not None:
        add_flags(parser, cls, title=f"{name} settings (also TOML keys of --config)",
                  groups=groups)
    add_common_flags(parser, bus=command.bus, config=cls is not None and command.config,
                     groups=groups)
    return parser


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slamlens", description="See whether an EKF-SLAM estimator is right.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, command in COMMANDS.items():
        sub.add_parser(name, help=command.help, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        parser = _parser()
        if not argv or argv[0] in {"-h", "--help"}:
            parser.print_help()
            return 0 if argv else 2
        parser.error(f"unknown command {argv[0]!r}; choose from {', '.join(COMMANDS)}")
    name = argv[0]
    args = command_parser(name).parse_args(argv[1:])
    keep_freed_memory()  # before the command starts any thread (common/memory.py)
    module = import_service_module(COMMANDS[name].module)
    return run_cli(lambda: module.run(name, args))


if __name__ == "__main__":
    sys.exit(main())
