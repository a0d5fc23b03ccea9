"""``seamap router``: the zenoh router of a fleet (see ``seamap.router``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "router",
        help="a zenoh router that a fleet's boats and shore stations connect to",
        description=(
            "Run a zenoh router (the zenoh library's own router mode) from a site file's "
            "[zenoh] table (config_file first: TLS, authentication, access control; then "
            "listen and connect; the mode is always router). Boats and shore stations "
            "connect to it as clients; vehicles are told apart by their id. Without "
            "--config it listens on tcp/127.0.0.1:7447. Tells which vehicles are alive "
            "every 10 s. Runs until Ctrl-C or SIGTERM (or --duration); exit status 0."
        ),
    )
    parser.add_argument(
        "--config", type=Path, metavar="SITE.toml", help="a site TOML file: its [zenoh] table"
    )
    parser.add_argument(
        "--listen", nargs="+", action="extend", metavar="ENDPOINT",
        help="endpoints to listen on (replace [zenoh] listen; default tcp/127.0.0.1:7447)",
    )  # fmt: skip
    parser.add_argument(
        "--connect", nargs="+", action="extend", metavar="ENDPOINT",
        help="other routers to connect to (replace [zenoh] connect)",
    )  # fmt: skip
    parser.add_argument(
        "--duration", type=float, metavar="S", help="stop after S seconds (default: never)"
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from daemon.config import load_config
    from seamap.router import router_settings, serve

    if args.duration is not None and not args.duration > 0:
        raise SeamapError(f"--duration {args.duration:g}: must be more than 0 seconds")
    config = load_config(args.config) if args.config is not None else None
    settings = router_settings(config, listen=args.listen, connect=args.connect)
    return serve(settings, args.duration)
