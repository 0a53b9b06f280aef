"""The `quadsr` console script: one subcommand per job, each registered by the package that owns it."""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING

from quadsr import __version__

if TYPE_CHECKING:
    import argparse

# Each module exposes register(subparsers) -> None, adding its subcommands with set_defaults(func=...).
# A subcommand's func takes the parsed args and returns an exit code.
COMMAND_MODULES = (
    "sitl.cli",
    "sitl.ardupilot_cli",
    "identification.cli",
    "controller.cli",
    "quadsr.pipeline_cli",
    "quadsr.campaign.cli",
    "quadsr.px4_cli",
)


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every available subcommand."""
    import argparse  # here, not at the top: `quadsr --version` imports nothing it does not need
    import importlib

    parser = argparse.ArgumentParser(
        prog="quadsr",
        description="Learn a quadrotor model with symbolic regression and fly it over MAVLink.",
    )
    parser.add_argument("--version", action="version", version=f"quadsr {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # that part is not built yet
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse, dispatch, and turn user mistakes into clear messages."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv == ["--version"]:  # answered before anything else is imported (argparse, numpy, sympy, ...)
        print(f"quadsr {__version__}")
        return 0
    from bridge.errors import UserError
    from bridge.shutdown import StopSignals

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    # SIGTERM acts as Ctrl-C (KeyboardInterrupt: each job writes what it has), and a repeated signal while
    # the job shuts down is absorbed (bridge.shutdown.StopSignals).
    signals = StopSignals(raise_interrupt=True)
    try:
        with signals:
            return int(args.func(args) or 0)
    except UserError as exc:
        print(f"quadsr {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"quadsr {args.command}: interrupted ({signals.name})", file=sys.stderr)
        return signals.exit_code
    except BrokenPipeError:  # output piped into `head` and the like: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
