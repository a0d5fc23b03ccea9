"""``seamap run --config FILE``: the boat daemon (see ``daemon.service``)."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "run",
        help="the boat daemon: record the sonar and the autopilot, map live, end surveys",
        description=(
            "Run the boat daemon: record every sonar message and MAVLink packet per survey, "
            "map live, and write the result folder when a survey ends (and on SIGTERM)."
        ),
    )
    parser.add_argument("--config", type=Path, required=True, help="the site TOML file")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from daemon.config import load_config
    from daemon.logs import configure_logging
    from daemon.service import Daemon

    config = load_config(args.config)
    configure_logging(config.daemon.log_level)
    # The event loop should get the GIL back quickly from the mapping thread: receive
    # stamps are taken on the loop.
    sys.setswitchinterval(0.001)
    return asyncio.run(Daemon(config).run())
