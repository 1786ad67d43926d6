"""The ``uavcal`` command.

Each sub-command lives in ``uavcal_jax/commands/<name>.py`` and exposes
``register(subparsers)``, which adds its parser and sets ``func(args) -> int``. Errors on bad
input (:class:`~uavcal_jax.errors.DataError`) are printed as one clear line, exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from uavcal_jax import __version__
from uavcal_jax.allocator import keep_freed_memory
from uavcal_jax.errors import DataError

#: Sub-command modules under ``uavcal_jax.commands``, in ``--help`` order.
COMMANDS = ("simulate", "info", "calib", "vio", "detect", "run", "demo")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uavcal",
        description="UAV perception in JAX: simulate flights, read EuRoC/ROS data, "
        "calibrate IMUs, run VIO, detect and follow targets.",
    )
    parser.add_argument("--version", action="version", version=f"uavcal-jax {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        importlib.import_module(f"uavcal_jax.commands.{name}").register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    keep_freed_memory()  # many similar XLA calls ahead: reuse their buffers' pages
    try:
        return int(args.func(args) or 0)
    except DataError as err:
        print(f"uavcal {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"uavcal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
