"""The ``seamap`` console script: one thin argparse front end over the packages.

Each subcommand lives in ``seamap/commands/<name>.py`` with ``register(subparsers)``
(adds its parser and sets ``handler``) and does no more than parse and call in. Bad input
ends with one line on stderr naming the thing and the reason, and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from seamap import __version__
from seamap.commands import (
    bench,
    ctl,
    demo,
    evaluate,
    info,
    replay,
    router,
    run,
    security,
    shore,
    simulate,
    survey,
)
from seamap.errors import SeamapError

COMMANDS = (
    info, simulate, replay, evaluate, run, ctl, shore, router, bench, demo, security, survey,
)  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="seamap",
        description="Georeferenced seabed mosaics from a forward-looking sonar and a Pixhawk.",
    )
    parser.add_argument("--version", action="version", version=f"seamap {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS:
        command.register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
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
    return status


if __name__ == "__main__":
    sys.exit(main())
