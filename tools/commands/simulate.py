"""``seamap simulate --scenario NAME --seed N --out DIR``: a deterministic simulated survey."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError


def register(subparsers: Any) -> None:
    from tools.sim import SCENARIOS

    parser = subparsers.add_parser(
        "simulate",
        help="simulate a survey: sonar.oculus, nav.tlog, truth.json, seabed.tif, site.toml",
        description=(
            "Simulate a sonar survey deterministically and write the raw logs as the boat "
            "would record them, with the truth to score a mosaic against."
        ),
    )
    parser.add_argument("--scenario", required=True, choices=sorted(SCENARIOS))
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument(
        "--flavour", choices=("ardupilot", "px4"), default=None, help="autopilot the tlog mimics"
    )
    parser.add_argument("--max-pings", type=int, default=None, help="stop after N pings")
    parser.add_argument("--beams", type=int, default=None, help="beams per ping (256 or 512)")
    parser.add_argument("--current", type=float, default=None, help="cross-current (m/s)")
    parser.set_defaults(handler=run)


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    overrides: dict[str, Any] = {}
    if args.flavour is not None:
        overrides["flavour"] = args.flavour
    if args.max_pings is not None:
        if args.max_pings < 1:
            raise SeamapError(f"--max-pings must be at least 1, got {args.max_pings}")
        overrides["max_pings"] = args.max_pings
    if args.beams is not None:
        overrides["n_beams"] = args.beams
    if args.current is not None:
        overrides["current_mps"] = args.current
    return overrides


def run(args: argparse.Namespace) -> int:
    from tools.sim import simulate

    summary = simulate(args.scenario, args.seed, args.out, **overrides_from_args(args))
    print(summary.describe())
    return 0
