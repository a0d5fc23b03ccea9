"""``seamap replay``: map recorded sonar and MAVLink logs into the contract's result folder."""

from __future__ import annotations

import argparse
import datetime as dt
import math
import sys
import time
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.errors import SeamapError

if TYPE_CHECKING:
    from daemon.replay import Scorer

MODES = ("single-stage", "two-stage", "fmt-only", "gps-only", "streaming")


_GROUPS = {
    "translation": "registrations' translations",
    "yaw": "registrations' rotations",
    "gnss": "GNSS positions",
    "gnss_velocity": "GNSS velocities",
}


def _widened(factors: dict[str, float]) -> str:
    """The groups whose sigmas the fusion widened to their residuals, as "translations
    2.4x their stated sigma, ..." (empty: none)."""
    parts = [
        f"{label} {math.sqrt(factors[name]):.1f}x"
        for name, label in _GROUPS.items()
        if factors.get(name, 1.0) > 1.0
    ]
    return ", ".join(parts) + " their stated sigma" if parts else ""


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "replay",
        help=(
            "map recorded logs: mosaic.tif, mosaic.png, trajectory.csv, coverage.tif, "
            "coverage.png, report.json (and gaps.geojson with --area)"
        ),
        description=(
            "Run the mapping pipeline over a recorded Oculus sonar log and a MAVLink log "
            "(or over the segments of a survey, in order) and write the result folder."
        ),
    )
    parser.add_argument(
        "--sonar",
        type=Path,
        action="append",
        help=(
            "Oculus log (.oculus v1 or v2) or raw network capture (Oculus messages back to "
            "back, as liboculus and driver tools record them; needs --sonar-start); repeat "
            "for the segments of one survey, in time order"
        ),
    )
    parser.add_argument(
        "--sonar-start",
        type=_when,
        default=None,
        metavar="TIME",
        help=(
            "a raw capture's first ping time (it has no receipt stamps): UNIX seconds or an "
            "ISO 8601 time with its zone (2026-05-03T10:15:02.250Z), the navigation log's clock"
        ),
    )
    parser.add_argument(
        "--sonar-rate",
        type=float,
        default=None,
        metavar="HZ",
        help=(
            "a raw capture's ping rate: pings 1/HZ apart (default: as the sonar's own clock "
            "in SimplePingResult v2 says; v1 pings need it)"
        ),
    )
    parser.add_argument(
        "--nav",
        type=Path,
        action="append",
        help="MAVLink log (.tlog or .bin); repeat for .tlog segments, in time order",
    )
    parser.add_argument(
        "--survey",
        type=Path,
        default=None,
        metavar="DIR",
        help="a recorded survey folder: replay all its segments (instead of --sonar/--nav)",
    )
    parser.add_argument("--config", type=Path, default=None, help="site TOML (default: defaults)")
    parser.add_argument("--mode", choices=MODES, default="single-stage")
    parser.add_argument("--out", type=Path, required=True, help="result folder")
    parser.add_argument(
        "--truth",
        type=Path,
        default=None,
        help=(
            "add accuracy to the report against a simulator's truth.json or a reference "
            "trajectory CSV (RTK+INS, total station: columns time,lat,lon,heading_deg, "
            "optional east,north, roll_deg,pitch_deg, altitude_m; told apart by content)"
        ),
    )
    add_truth_matching(parser)
    parser.add_argument(
        "--area",
        type=Path,
        default=None,
        metavar="AREA.geojson",
        help=(
            "the survey's area (GeoJSON polygon, holes kept out, or a lat,lon list): its "
            "covered fraction in the report and what was missed in gaps.geojson"
        ),
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help=(
            "worker processes for the live engine's stages (streaming; default: [daemon] "
            "workers, the cores less one; 0: all in this process); the map is the same"
        ),
    )
    parser.set_defaults(handler=run)


def _when(text: str) -> float:
    """A time given on the command line: UNIX seconds, or ISO 8601 with its zone."""
    try:
        return float(text)
    except ValueError:
        pass
    try:
        stamp = dt.datetime.fromisoformat(text.replace("Z", "+00:00").replace("z", "+00:00"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is neither UNIX seconds nor an ISO 8601 time"
        ) from None
    if stamp.tzinfo is None:
        raise argparse.ArgumentTypeError(
            f"{text!r} has no zone: add Z (UTC) or an offset such as +02:00"
        )
    return stamp.timestamp()


def add_truth_matching(parser: argparse.ArgumentParser) -> None:
    """``--truth-tolerance`` and ``--truth-max-gap``: how a reference trajectory's rows
    are matched to the frames (``seamap replay`` and ``seamap evaluate``)."""
    parser.add_argument(
        "--truth-tolerance",
        type=float,
        default=None,
        metavar="S",
        help=(
            "a reference trajectory row this close (s) to a frame's time stands for it when "
            "it cannot be interpolated (default: half the median ping interval, so a row "
            "is nearest to one frame only)"
        ),
    )
    parser.add_argument(
        "--truth-max-gap",
        type=float,
        default=1.0,
        metavar="S",
        help=(
            "interpolate a frame's reference pose between the rows before and after it "
            "when they are at most this far apart (s; %(default)s); frames matched "
            "neither way are left out and counted"
        ),
    )


def truth_matching(args: argparse.Namespace) -> dict[str, Any]:
    """The checked ``--truth-tolerance`` / ``--truth-max-gap`` as the scorer's keywords."""
    for flag, value in (("--truth-tolerance", args.truth_tolerance),
                        ("--truth-max-gap", args.truth_max_gap)):  # fmt: skip
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise SeamapError(f"{flag} {value}: must be 0 or more seconds")
    return {"tolerance_s": args.truth_tolerance, "max_gap_s": args.truth_max_gap}


class Progress:
    """One self-rewriting line on a terminal; silent when stderr is not a terminal."""

    def __init__(self) -> None:
        self.enabled = sys.stderr.isatty()
        self.last = 0.0

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if done < total and now - self.last < 0.2:
            return
        self.last = now
        sys.stderr.write(f"\r{stage}: {done}/{total} frames ")
        sys.stderr.flush()

    def done(self) -> None:
        if self.enabled:
            sys.stderr.write("\r" + " " * 60 + "\r")
            sys.stderr.flush()


SCORERS = "seamap.scorers"
"""The entry-point group of what scores a result against a reference: ``truth`` takes
``--truth`` (installed with the simulator's tools)."""


def truth_scorer(path: Path, **matching: Any) -> Scorer:
    """The installed ``truth`` scorer bound to ``path`` (a simulator's truth.json or a
    reference trajectory CSV; ``matching``: ``tolerance_s``, ``max_gap_s``); SeamapError
    when the file is missing, is neither, or no scorer is installed."""
    if not path.is_file():
        raise SeamapError(f"--truth {path}: no such file")
    found = [e for e in entry_points(group=SCORERS) if e.name == "truth"]
    if not found:
        raise SeamapError(f"--truth {path}: no truth scorer is installed (the seamap tools)")
    scorer: Scorer = found[0].load()(path, **matching)
    return scorer


def run(args: argparse.Namespace) -> int:
    from daemon.config import load_config
    from daemon.replay import replay, replay_survey

    if args.survey is not None and (args.sonar or args.nav):
        raise SeamapError("--survey replays every segment of the folder: not with --sonar/--nav")
    if args.survey is None:
        if not (args.sonar and args.nav):
            raise SeamapError("give --sonar and --nav (or --survey DIR)")
        for label, paths in (("sonar log", args.sonar), ("navigation log", args.nav)):
            for path in paths:
                if not path.exists():
                    raise SeamapError(f"{path}: no such {label}")
                if path.is_dir():
                    raise SeamapError(f"{path}: is a directory, not a {label}")
    if args.workers is not None and args.workers < 0:
        raise SeamapError(f"--workers must be 0 or more, got {args.workers}")
    clock = None
    if args.sonar_start is not None:
        if args.survey is not None:
            raise SeamapError("--sonar-start stamps a raw capture given by --sonar, not --survey")
        from drivers.oculus.logfile import CaptureClock

        clock = CaptureClock(args.sonar_start, args.sonar_rate)
    elif args.sonar_rate is not None:
        raise SeamapError("--sonar-rate spaces a raw capture's pings: give --sonar-start too")
    matching = truth_matching(args)
    scorer = truth_scorer(args.truth, **matching) if args.truth is not None else None
    progress = Progress()
    try:
        if args.survey is not None:
            report = replay_survey(
                args.survey,
                load_config(args.config),
                args.out,
                mode=args.mode,
                scorer=scorer,
                progress=progress,
                area=args.area,
                workers=args.workers,
            )
        else:
            report = replay(
                args.sonar,
                args.nav,
                args.config,
                args.mode,
                args.out,
                scorer=scorer,
                progress=progress,
                area=args.area,
                workers=args.workers,
                clock=clock,
            )
    finally:
        progress.done()
    frames = report["frames"]
    print(
        f"{args.out}: {frames['mapped']} of {frames['read']} frames mapped "
        f"({args.mode}, {report['timings_s']['total']:.1f} s)"
    )
    for reason, count in sorted(frames["rejected"].items()):
        print(f"  rejected {count}: {reason}")
    unregistered = frames.get("placed_without_registration", 0)
    if unregistered:
        print(f"  {unregistered} placed without a registration (odometry and GNSS)")
    widened = _widened(report.get("fusion", {}).get("variance_factors", {}))
    if widened:
        print(f"  weighed by their residuals: {widened}")
    coverage = report["coverage"]
    line = f"  coverage: {coverage['covered_m2']:.0f} m² seen by {coverage['min_passes']}+ passes"
    if "area" in coverage:
        area = coverage["area"]
        line += (
            f"; {100 * area['covered_fraction']:.1f} % of the area, "
            f"{area['gaps']} gaps of {area['gaps_m2']:.0f} m²"
        )
    print(line)
    if "accuracy" in report:
        accuracy = report["accuracy"]
        ate = accuracy["trajectory"]["rmse"]
        spacing = accuracy.get("quadrat_spacing", {})
        line = f"  accuracy: ATE {ate:.3f} m"
        if spacing.get("rmse") is not None:
            line += f", quadrat spacing RMSE {spacing['rmse']:.3f} m"
        left_out = accuracy.get("reference", {}).get("mapped_without_reference", 0)
        if left_out:
            line += f" ({left_out} mapped frames without a reference pose left out)"
        print(line)
        if accuracy.get("unavailable"):
            print(f"  {accuracy['unavailable']}")
    return 0
