"""``seamap ctl --config FILE status|start|stop [--area AREA]``: talk to the running daemon."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "ctl",
        help="ask the running daemon for its status, or to start or stop a survey",
        description=(
            "Talk to the running daemon through its control socket (state_dir/control.sock): "
            "status prints its health as JSON; start opens a survey (--area: the area it is "
            "to cover, for the covered fraction live and the gaps at the end); stop ends it "
            "(the survey-end pass then writes the result folder)."
        ),
    )
    parser.add_argument("action", choices=("status", "start", "stop"))
    parser.add_argument("--config", type=Path, help="the daemon's site TOML file")
    parser.add_argument(
        "--area",
        type=Path,
        help="with start: the survey's area (GeoJSON polygon, holes kept out, or a lat,lon "
        "list), instead of the config's [mission] area",
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from daemon.config import load_config
    from daemon.control import request

    config = load_config(args.config)
    extra: dict[str, Any] = {}
    if args.area is not None:
        if args.action != "start":
            raise SeamapError(f"--area goes with start, not {args.action}")
        from drivers.formats.area import area_geojson, read_area

        extra["area"] = area_geojson(read_area(args.area))
    reply = request(Path(config.daemon.state_dir) / "control.sock", args.action, **extra)
    if not reply.get("ok"):
        raise SeamapError(f"the daemon refused: {reply.get('error')}")
    if args.action == "status":
        print(json.dumps(reply["status"], indent=2))
    elif reply.get("survey") is None:
        print("no survey was open" if args.action == "stop" else "no survey")
    else:
        print(reply["survey"])
    return 0
