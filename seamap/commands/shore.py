"""``seamap shore``: the shore station, following a boat's live map over zenoh (see
``seamap.shore.station``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "shore",
        help="the shore station: follow a boat's live map over zenoh and keep it on disk",
        description=(
            "Follow a boat's live mosaic, pose and status over zenoh and keep them under "
            "DIR: {vehicle}/{survey}/mosaic.tif and mosaic.png, {vehicle}/track.csv and "
            "track.geojson, {vehicle}/status.json, rewritten every 5 s. Catches up with every "
            "current tile at start and whenever the boat comes back. Runs until Ctrl-C or "
            "SIGTERM (or --duration), then writes its files one last time. With --web, also "
            "serves a live map page of every boat followed."
        ),
    )
    parser.add_argument(
        "--config",
        type=Path,
        metavar="SITE.toml",
        help="a site TOML file: its [zenoh] session and [daemon] vehicle",
    )
    parser.add_argument(
        "--connect",
        nargs="+",
        action="extend",
        metavar="ENDPOINT",
        help="zenoh endpoints to connect to (default without --config: tcp/127.0.0.1:7447)",
    )
    parser.add_argument(
        "--listen",
        nargs="+",
        action="extend",
        metavar="ENDPOINT",
        help="zenoh endpoints to listen on (default without --config: none)",
    )
    parser.add_argument(
        "--mode", choices=("peer", "client"), help="zenoh session mode (default: peer)"
    )
    parser.add_argument(
        "--vehicle",
        metavar="ID",
        help="the vehicle id to follow (default: the config's [daemon] vehicle, else every one)",
    )
    parser.add_argument(
        "--survey", metavar="ID", help="the survey id to follow (default: every survey)"
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument(
        "--duration", type=float, metavar="S", help="stop after S seconds (scripts, tests)"
    )
    parser.add_argument(
        "--web",
        metavar="[HOST:]PORT",
        help="also serve the live map page there (host 127.0.0.1 unless given; port 0: a "
        "free port); its address is printed once it serves",
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from daemon.config import load_config
    from seamap.shore import serve, shore_settings

    web = None
    if args.web is not None:
        from seamap.shore.web import parse_web_address  # aiohttp only when the page is wanted

        web = parse_web_address(args.web)
    if args.duration is not None and not args.duration > 0:
        raise SeamapError(f"--duration {args.duration:g}: must be more than 0 seconds")
    config = load_config(args.config) if args.config is not None else None
    settings = shore_settings(
        args.out,
        config,
        mode=args.mode,
        listen=args.listen,
        connect=args.connect,
        vehicle=args.vehicle,
        survey=args.survey,
    )
    return serve(settings, args.duration, web)
