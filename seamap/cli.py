"""The ``seamap`` console script: one thin argparse front end over the packages.

Each product subcommand lives in ``seamap/commands/<name>.py`` with
``register(subparsers)`` (adds its parser and sets ``handler``) and does no more than parse
and call in. The development tools' subcommands (``simulate``, ``evaluate``, ``bench``,
``demo``: the simulator and the paper's evaluation, in ``tools``) come in through the
``seamap.commands`` entry-point group, as rasterio's ``rio`` loads its commands: the
product never imports ``tools``, and a product command (``seamap run``, the boat's
service) loads none of them. Bad input ends with one line on stderr naming the thing and
the reason, and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points

from drivers.errors import SeamapError
from seamap import __version__
from seamap.commands import ctl, info, replay, router, run, security, shore, survey

COMMANDS = {
    "info": info, "replay": replay, "run": run, "ctl": ctl, "shore": shore,
    "router": router, "security": security, "survey": survey,
}  # fmt: skip
PLUGIN_GROUP = "seamap.commands"
"""The entry-point group of the subcommands installed beside the product's own (each
names a ``register(subparsers)``)."""


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser with every product command, and the installed plugin commands unless
    ``argv`` names a product command (so ``seamap run`` imports no plugin)."""
    parser = argparse.ArgumentParser(
        prog="seamap",
        description="Georeferenced seabed mosaics from a forward-looking sonar and a Pixhawk.",
    )
    parser.add_argument("--version", action="version", version=f"seamap {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS.values():
        command.register(subparsers)
    words = [a for a in (sys.argv[1:] if argv is None else argv) if not a.startswith("-")]
    if not words or words[0] not in COMMANDS:
        for plugin in sorted(entry_points(group=PLUGIN_GROUP), key=lambda e: e.name):
            if plugin.name not in COMMANDS:
                plugin.load()(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    try:
        status: int = args.handler(args)
    except SeamapError as exc:
        print(f"seamap {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"seamap {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # Output piped into `head` and closed early: not an error worth a traceback.
        sys.stderr.close()
        return 0
    except OSError as exc:
        # The machine, not the input: a full disk, a folder that cannot be written. What
        # was written before stays (results go to a temporary name, then renamed).
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"seamap {args.command}: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    return status


if __name__ == "__main__":
    sys.exit(main())
