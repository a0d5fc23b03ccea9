"""``seamap demo [--out DIR]``: the main job on one machine.

For now (the live system, its drivers and zenoh come in later issues) the demo simulates
the paper's quadrat survey, tells what the recorded logs hold, maps them with the
single-stage pipeline as ``seamap replay`` would, and scores the mosaic against the
simulator's truth.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any


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
    from seamap.commands.info import format_summary, summarize
    from seamap.commands.replay import Progress
    from seamap.replay import replay
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

    result = args.out / "result"
    print(f"[3/3] mapping the survey (single-stage) into {result}")
    progress = Progress()
    try:
        report = replay(
            survey / "sonar.oculus",
            survey / "nav.tlog",
            survey / "site.toml",
            "single-stage",
            result,
            truth=survey / "truth.json",
            progress=progress,
        )
    finally:
        progress.done()
    frames = report["frames"]
    timings = report["timings_s"]
    print(
        f"      {frames['mapped']} of {frames['read']} frames mapped in {timings['total']:.1f} s "
        f"({1000 * timings['total'] / max(frames['read'], 1):.0f} ms a frame), "
        f"{frames['loop_closures']['kept']} loop closures"
    )
    accuracy = report["accuracy"]
    trajectory = accuracy["trajectory"]
    spacing = accuracy["quadrat_spacing"]
    print(
        f"      trajectory error {trajectory['rmse']:.2f} m (GPS-limited), "
        f"{trajectory['aligned_rmse']:.3f} m in shape; quadrat spacing RMSE "
        f"{spacing['rmse'] * 100:.1f} cm over {int(spacing['located'])} quadrats"
    )
    print(f"      mosaic: {result / 'mosaic.tif'} (and mosaic.png, trajectory.csv, report.json)")
    print(f"demo output in {args.out.resolve()}")
    return 0
