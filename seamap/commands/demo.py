"""``seamap demo [--out DIR]``: the main job on one machine.

For now (the mapping core and the live system come in later issues) the demo simulates
the paper's quadrat survey and reads everything back through seamap's own readers:
every ping and every navigation sample, and prints what it found.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from seamap.config import load_config


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="run the whole system on this machine (for now: simulate a survey, read it back)",
    )
    parser.add_argument("--out", type=Path, default=Path("demo-out"), help="output folder")
    parser.add_argument("--scenario", default="quadrats", help="simulator scenario")
    parser.add_argument("--seed", type=int, default=1)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from drivers.mavlink import read_nav_log
    from drivers.oculus.logfile import LogReadReport, iter_pings
    from seamap.commands.info import format_summary, summarize
    from tools.sim import simulate

    survey = args.out / "survey"
    print(f"[1/3] simulating the '{args.scenario}' survey (seed {args.seed}) into {survey}")
    started = time.monotonic()
    summary = simulate(args.scenario, args.seed, survey)
    print(summary.describe())
    print(f"      done in {time.monotonic() - started:.1f} s")

    print("[2/3] what the logs hold (seamap info)")
    for name in ("sonar.oculus", "nav.tlog"):
        print(format_summary(survey / name, summarize(survey / name)))

    print("[3/3] reading every ping and navigation sample back")
    config = load_config(survey / "site.toml")
    report = LogReadReport()
    n_pings = 0
    peak = 0
    for ping in iter_pings(survey / "sonar.oculus", report):
        n_pings += 1
        peak = max(peak, int(ping.image.max()))
    nav = read_nav_log(
        survey / "nav.tlog",
        heading_source=config.mavlink.heading_source,
        imu_source=config.mavlink.imu_source,
        declination_deg=config.mavlink.declination_deg,
    )
    print(f"      sonar: {n_pings} pings, {report.corrupt_pings} corrupt, brightest sample {peak}")
    print(
        f"      nav ({nav.autopilot}): {len(nav.imu)} IMU samples ({nav.imu_source}), "
        f"{len(nav.gnss)} GNSS fixes, {len(nav.heading)} headings ({nav.heading_source})"
    )
    print(f"demo output in {args.out.resolve()}")
    return 0
