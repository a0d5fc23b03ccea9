"""``seamap bench [--json]``: throughput, latency and memory of the streaming engine."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="measure the streaming engine over a simulated survey (speed, latency, memory)",
        description=(
            "Run the streaming mapping engine in this process over a simulated survey and "
            "report milliseconds per frame per stage, frames per second, the multiple of "
            "real time at 10 Hz, latency and memory. OpenCV runs on one thread."
        ),
    )
    parser.add_argument("--scenario", default="quadrats", help="simulator scenario")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--pings", type=int, default=None, help="stop after N pings")
    parser.add_argument("--beams", type=int, default=None, help="beams per ping")
    parser.add_argument(
        "--range",
        type=float,
        default=None,
        metavar="M",
        dest="range_m",
        help="the sonar's range (m; default the scenario's); its range resolution follows, "
        "as the M1200d's does (about range / 600 beyond 6 m)",
    )
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1)")
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        metavar="N",
        help="worker processes for the engine's stages (default 0: all in this process)",
    )
    parser.add_argument(
        "--final",
        action="store_true",
        help="also time the survey-end pass (the pings are recorded as the daemon records "
        "them, and the pass reads the recording)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--plot", type=Path, default=None, metavar="PNG", help="draw the memory curve there"
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import cv2

    if args.workers < 0:
        raise SeamapError(f"--workers must be 0 or more, got {args.workers}")
    if args.pings is not None and args.pings < 1:
        raise SeamapError(f"--pings must be at least 1, got {args.pings}")
    if args.plot is not None and not args.plot.parent.is_dir():
        raise SeamapError(f"--plot {args.plot}: no folder {args.plot.parent} to write it in")
    # OpenCV's thread count is process-wide and changes the last bits of its sums: put it
    # back afterwards, so a bench run inside another program leaves its results alone.
    threads = cv2.getNumThreads()
    cv2.setNumThreads(args.threads)
    try:
        return _bench(args)
    finally:
        cv2.setNumThreads(threads)


def _bench(args: argparse.Namespace) -> int:
    from tools.bench import format_table, plot_memory, run_bench

    overrides: dict[str, Any] = {}
    if args.beams is not None:
        overrides["n_beams"] = args.beams
    if args.range_m is not None:
        overrides["range_m"] = args.range_m

    def progress(stage: str, done: int, total: int) -> None:
        if sys.stderr.isatty():
            sys.stderr.write(f"\r{stage}: {done}/{total} frames ")
            sys.stderr.flush()

    result = run_bench(
        args.scenario,
        args.seed,
        args.pings,
        overrides,
        final_pass=args.final,
        progress=progress,
        workers=args.workers,
    )
    if sys.stderr.isatty():
        sys.stderr.write("\r" + " " * 50 + "\r")
    if args.json:
        print(json.dumps(result.as_json(), sort_keys=True))
    else:
        print(format_table(result))
    if args.plot is not None:
        try:
            plot_memory(result, args.plot)
        except OSError as exc:
            raise SeamapError(f"--plot {args.plot}: cannot write it ({exc.strerror})") from None
    return 0
