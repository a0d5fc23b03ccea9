"""``seamap demo [--out DIR] [--zenoh-listen ENDPOINT] [--secure]``: the whole system on loopback
(``tools.demo``): emulators play a simulated survey, the daemon maps it live and publishes
on zenoh, the shore station follows, and the result is scored against the truth."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="the whole system on this machine: emulators, daemon, zenoh, shore station",
        description=(
            "Simulate a survey; play it through the sonar and autopilot emulators on "
            "127.0.0.1; the daemon (seamap run) records, maps and publishes it on zenoh "
            "(vehicle 'demo'); the shore station (seamap shore) follows; at the end the "
            "survey-end pass writes the result and the accuracy against the truth is printed."
        ),
    )
    parser.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    parser.add_argument(
        "--zenoh-listen",
        default="tcp/127.0.0.1:7447",
        help="the daemon's zenoh endpoint (default tcp/127.0.0.1:7447)",
    )
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

    return run_demo(
        DemoOptions(
            args.out, args.scenario, args.seed, args.zenoh_listen, args.max_pings, args.secure
        )
    )
