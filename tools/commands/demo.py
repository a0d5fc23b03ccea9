"""``seamap demo [--out DIR] [--boats N] [--web [HOST:]PORT] [--zenoh-listen ENDPOINT]
[--secure]``: the whole system on loopback (``tools.demo``): emulators play simulated
surveys, the daemons map them live and publish through a zenoh router, the shore station
follows (and serves the live map page), and the results are scored against the truth."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="the whole system on this machine: emulators, daemon, zenoh, shore station",
        description=(
            "Simulate a survey for each boat (neighbouring areas); play each through the sonar "
            "and autopilot emulators on 127.0.0.1; each boat's daemon (seamap run) records, "
            "maps and publishes it through a zenoh router (seamap router; vehicles 'demo', "
            "'demo2', ...); the shore station (seamap shore) follows every boat; at the end "
            "the survey-end passes write the results and the accuracy against the truth is "
            "printed. With --web the shore serves the live map page, and the demo stays up "
            "after the surveys until Ctrl-C or SIGTERM."
        ),
    )
    parser.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    parser.add_argument(
        "--zenoh-listen",
        default="tcp/127.0.0.1:7447",
        help="the router's zenoh endpoint (default tcp/127.0.0.1:7447; with --secure the "
        "boat's own)",
    )
    parser.add_argument("--boats", type=int, default=1, help="simulated boats (1 to 4)")
    parser.add_argument(
        "--web", metavar="[HOST:]PORT",
        help="serve the shore's live map page there (host 127.0.0.1 unless given)",
    )  # fmt: skip
    parser.add_argument("--scenario", default="quadrats", help="simulator scenario")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-pings", type=int, help="cut the survey short (pings)")
    parser.add_argument(
        "--secure", action="store_true",
        help="run the zenoh link on a set `seamap security init` makes (in OUT/security): "
        "TLS with certificates on both sides, the shore's password, the boat's access rules",
    )  # fmt: skip
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from tools.demo import DemoOptions, run_demo

    options = DemoOptions(
        args.out, args.scenario, args.seed, args.zenoh_listen, args.max_pings, args.secure,
        args.boats, args.web,
    )  # fmt: skip
    return run_demo(options)
