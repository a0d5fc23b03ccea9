"""``seamap survey plan|replan|start|status|pause|resume|abort``: survey missions on the
autopilot.

``plan`` turns an area into a QGroundControl ``.plan`` (``daemon.plan_files``), ``replan``
what a survey missed of it (``daemon.replan_files``); the others talk to the autopilot
through MAVSDK (``drivers.mission``). ``start`` then asks the boat daemon over zenoh to
open a survey. Exit status: 0 done (for ``replan`` also when there is nothing to
re-plan: it says so and writes nothing); 2 refused (one line on stderr, nothing started
or written); 1 the mission runs but the daemon did not open a survey.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import sys
from collections.abc import Sized
from pathlib import Path
from typing import Any

from drivers.errors import SeamapError

TIMEOUT_HELP = "the longest one step may take, in seconds (default %(default)s)"


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "survey",
        help="plan a survey mission, start it on the autopilot, follow and steer it",
        description=(
            "Survey missions on the autopilot (ArduPilot Rover or PX4) through MAVSDK. "
            "--connect takes udpin://HOST:PORT (listen), udpout://HOST:PORT (send to) or "
            "serial:///dev/ttyX:BAUD."
        ),
    )
    actions = parser.add_subparsers(dest="survey_command", metavar="ACTION", required=True)

    plan = actions.add_parser(
        "plan",
        help="lanes over an area as a QGroundControl .plan",
        description="Lawnmower lanes over a GeoJSON area, written as a QGroundControl .plan.",
    )
    plan.add_argument("--area", type=Path, required=True, help="the area, a GeoJSON polygon")
    plan.add_argument(
        "--spacing",
        type=float,
        help="lane spacing in metres (default: from the sonar's swath and --overlap)",
    )
    plan.add_argument("--overlap", type=float, help="overlap of neighbouring swaths, 0..1")
    plan.add_argument(
        "--angle",
        type=float,
        help="lane direction, degrees from north (default: along the area's longest side)",
    )
    plan.add_argument("--speed", type=float, default=1.0, help="survey speed, m/s (%(default)s)")
    plan.add_argument(
        "--lead-in",
        type=float,
        default=5.0,
        help="straight run before each lane, metres (%(default)s)",
    )
    plan.add_argument(
        "--entry",
        choices=("nw", "ne", "sw", "se", "auto"),
        default="auto",
        help="corner to start from (%(default)s)",
    )
    plan.add_argument(
        "--firmware",
        choices=("ardupilot", "px4"),
        default="ardupilot",
        help="autopilot the plan is for (%(default)s)",
    )
    plan.add_argument("--config", type=Path, help="the site TOML file (sonar mount and range)")
    plan.add_argument("--out", type=Path, required=True, help="the .plan file to write")
    plan.set_defaults(handler=run_plan)

    replan = actions.add_parser(
        "replan",
        help="lanes over what a survey missed of its area, as a QGroundControl .plan",
        description=(
            "Lanes over the gaps a survey left in its area: the area (holes left out) less "
            "the cells its coverage.tif says were seen well enough (band 3, meets_bar), "
            "each part of at least --min-gap m². Each gap, or group of nearby gaps, gets "
            "lanes at its own bearing, and the groups are taken in the order that shortens "
            "the way from where the boat is, round the keep-outs. Written as survey plan "
            "writes a plan (.plan, .waypoints, .geojson, .png), for seamap survey start. "
            "With no gap it prints 'nothing to re-plan', writes nothing and exits 0."
        ),
    )
    source = replan.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--survey",
        type=Path,
        metavar="DIR",
        help="the survey's result folder: its coverage.tif, and its trajectory.csv's last "
        "row as where the boat starts",
    )
    source.add_argument("--coverage", type=Path, metavar="TIF", help="a coverage.tif")
    replan.add_argument(
        "--area", type=Path, required=True, help="the survey's area, a GeoJSON polygon"
    )
    replan.add_argument(
        "--min-gap",
        metavar="M2",
        help="the smallest gap to re-plan, m² (default: the config's [coverage] min_gap_m2)",
    )
    replan.add_argument(
        "--spacing",
        metavar="M",
        help="lane spacing in metres (default: from the sonar's swath, as survey plan)",
    )
    replan.add_argument(
        "--from",
        dest="start",
        metavar="LAT,LON",
        help="where the boat is, decimal degrees (south or west: --from=-33.86,151.21; "
        "default: the survey's last position, else the area's first vertex)",
    )
    replan.add_argument("--speed", metavar="MPS", default="1.0", help="survey speed, m/s (1.0)")
    replan.add_argument(
        "--lead-in", metavar="M", default="5.0", help="straight run before each lane, m (5.0)"
    )
    replan.add_argument(
        "--firmware",
        choices=("ardupilot", "px4"),
        default="ardupilot",
        help="autopilot the plan is for (%(default)s)",
    )
    replan.add_argument("--config", type=Path, help="the site TOML file (sonar, [coverage])")
    replan.add_argument(
        "--out", type=Path, required=True, metavar="GAPS.plan", help="the .plan file to write"
    )
    replan.set_defaults(handler=run_replan)

    start = actions.add_parser(
        "start",
        help="upload a .plan, check it, arm, start it and open a survey on the daemon",
        description=(
            "Upload PLAN.plan to the autopilot, read it back and compare, arm, start the "
            "mission (AUTO) and ask the boat daemon over zenoh to open a survey. Refuses, "
            "with nothing started, without a 3D GPS fix and a home position, when the "
            "upload fails or reads back different, or when the autopilot will not arm."
        ),
    )
    start.add_argument("plan", type=Path, help="a QGroundControl .plan file")
    _connect_arguments(start)
    start.add_argument(
        "--config", type=Path, help="a site TOML file: the daemon's [daemon] vehicle and [zenoh]"
    )
    start.add_argument(
        "--daemon",
        metavar="ENDPOINT",
        help="the daemon's zenoh endpoint, e.g. tcp/192.168.1.10:7447",
    )
    start.add_argument("--vehicle", help="the daemon's vehicle id (with --daemon)")
    start.add_argument(
        "--firmware", choices=("ardupilot", "px4"), help="override the plan's mission.firmwareType"
    )
    start.set_defaults(handler=run_start)

    for name, what in (
        ("status", "the mission's progress (current item of total), mode and arming"),
        ("pause", "hold where the boat is (HOLD)"),
        ("resume", "continue the mission (AUTO)"),
        ("abort", "give up the mission and return to launch (RTL)"),
    ):
        action = actions.add_parser(name, help=what, description=what[0].upper() + what[1:] + ".")
        _connect_arguments(action)
        if name == "status":
            action.add_argument("--json", action="store_true", help="print one JSON object")
        action.set_defaults(handler=run_steer)


def _connect_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--connect", metavar="URL", required=True, help="the autopilot's MAVLink link (MAVSDK URL)"
    )
    parser.add_argument("--timeout", type=float, default=20.0, help=TIMEOUT_HELP)


def _check_timeout(args: argparse.Namespace) -> None:
    if not args.timeout > 0:
        raise SeamapError(f"--timeout {args.timeout:g}: must be more than 0 seconds")


def run_plan(args: argparse.Namespace) -> int:
    from daemon.config import load_config

    config = load_config(args.config)
    options: dict[str, Any] = {
        "spacing_m": args.spacing,
        "angle_deg": args.angle,
        "speed_mps": args.speed,
        "lead_in_m": args.lead_in,
        "entry": args.entry,
        "firmware": args.firmware,
    }
    if args.overlap is not None:
        options["overlap"] = args.overlap
    planner: Any = importlib.import_module("daemon.plan_files")
    summary: dict[str, Any] = planner.plan_survey(args.area, args.out, config, **options)
    print(format_plan_summary(args.out, summary))
    return 0


def format_plan_summary(out: Path, summary: dict[str, Any]) -> str:
    lines = [
        f"{out}: {_lanes(summary)}",
        f"  {_length(summary)}; covers {_covered(summary)}",
    ]
    lines += [f"  wrote {path}" for path in summary.get("files") or ()]
    return "\n".join(lines)


def _lanes(summary: dict[str, Any]) -> str:
    def count(value: Any) -> int:
        return len(value) if isinstance(value, Sized) else int(value)

    spacing = f"spacing {summary['spacing_m']:.2f} m"
    if "swath_m" in summary and "overlap" in summary:
        spacing += f" (swath {summary['swath_m']:.2f} m, overlap {100 * summary['overlap']:.0f} %)"
    angles = summary.get("angles_deg") or [summary["angle_deg"]]
    unique = sorted(set(angles), key=angles.index)
    return (
        f"{count(summary['lanes'])} lanes, {count(summary['waypoints'])} waypoints, "
        f"{spacing}, lanes at {', '.join(f'{a:.1f}°' for a in unique)} from north"
    )


def _length(summary: dict[str, Any]) -> str:
    return f"{summary['distance_m'] / 1000:.2f} km, about {summary['duration_s'] / 60:.0f} min"


def _covered(summary: dict[str, Any]) -> str:
    area, covered = float(summary["area_m2"]), float(summary["covered_m2"])
    coverage = 100.0 * covered / area if area > 0 else 100.0 * float(summary["coverage"])
    return f"{covered:.0f} of {area:.0f} m² ({coverage:.1f} %)"


def run_replan(args: argparse.Namespace) -> int:
    from daemon.config import load_config

    options: dict[str, Any] = {
        "survey": args.survey,
        "coverage": args.coverage,
        "min_gap_m2": None if args.min_gap is None else _number("--min-gap", args.min_gap),
        "spacing_m": None if args.spacing is None else _number("--spacing", args.spacing),
        "speed_mps": _number("--speed", args.speed),
        "lead_in_m": _number("--lead-in", args.lead_in),
        "firmware": args.firmware,
        "start": None if args.start is None else _latlon("--from", args.start),
    }
    config = load_config(args.config)
    planner: Any = importlib.import_module("daemon.replan_files")
    summary: dict[str, Any] = planner.replan_survey(args.area, args.out, config, **options)
    print(format_replan_summary(args.out, summary))
    return 0


def _number(option: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise SeamapError(f"{option} {text!r}: not a number") from None
    if not math.isfinite(value):
        raise SeamapError(f"{option} {text!r}: not a finite number")
    return value


def _latlon(option: str, text: str) -> tuple[float, float]:
    parts = text.replace(";", ",").split(",")
    if len(parts) != 2:
        raise SeamapError(f"{option} {text!r}: expected LAT,LON in decimal degrees")
    lat, lon = (_number(option, part.strip()) for part in parts)
    if abs(lat) > 90 or abs(lon) > 180:
        raise SeamapError(f"{option} {text!r}: latitude or longitude out of range (LAT,LON)")
    return lat, lon


def _many(count: int, thing: str) -> str:
    return f"{count} {thing}" if count == 1 else f"{count} {thing}s"


def format_replan_summary(out: Path, summary: dict[str, Any]) -> str:
    """What ``seamap survey replan`` prints: the gaps, then the plan as ``survey plan``
    prints it, with how much of the gaps it maps; or that there is nothing to re-plan."""
    survey = summary["survey"]
    seen = f"the survey covered {100 * survey['covered_fraction']:.1f} % of the area"
    if not summary["gaps"]:
        return (
            f"{out}: nothing to re-plan: {seen} ({survey['covered_m2']:.0f} of "
            f"{survey['area_m2']:.0f} m²) and left no gap of {summary['min_gap_m2']:g} m² "
            "or more; no plan written"
        )
    gaps = (
        f"{out}: {_many(summary['gaps'], 'gap')} of {summary['min_gap_m2']:g} m² or more, "
        f"{summary['gaps_m2']:.0f} m² ({seen}), in {_many(summary['groups'], 'group')}"
    )
    if summary["unreachable"]:
        gaps += (
            f"; {summary['unreachable']} ({summary['unreachable_m2']:.0f} m²) no lane reaches "
            "(within the clearance of a hole)"
        )
    lat, lon = summary["start"]
    lines = [
        gaps,
        f"  {_lanes(summary)}",
        f"  {_length(summary)}, {summary['approach_m']:.0f} m from {summary['start_from']} "
        f"({lat:.7f},{lon:.7f}) to the first lane; covers {_covered(summary)} of the gaps",
    ]
    lines += [f"  wrote {path}" for path in summary.get("files") or ()]
    return "\n".join(lines)


def run_start(args: argparse.Namespace) -> int:
    import asyncio

    from daemon import request
    from daemon.config import load_config
    from drivers import mission
    from drivers.formats.area import parse_area

    _check_timeout(args)
    # Everything that can be wrong with the command line is found before the boat moves.
    plan = mission.load_plan(args.plan)
    url = mission.mavsdk_url(args.connect)
    config = load_config(args.config) if args.config is not None else None
    target = request.daemon_target(config, args.daemon, args.vehicle)
    firmware = mission.Firmware(args.firmware) if args.firmware else None
    if plan.area is not None:  # checked before the boat moves: the daemon would refuse it
        parse_area(json.dumps(plan.area), f"{args.plan}: the plan's seamap.area")

    started = asyncio.run(mission.start_survey(plan, url, args.timeout, firmware))
    ready = started.readiness
    print(
        f"mission started: {started.plan_items} items of {args.plan} on {started.firmware.value} "
        f"({started.items_sent} uploaded and read back), "
        f"{'already armed' if started.was_armed else 'armed'}, AUTO; "
        f"GPS {ready.fix} with {ready.satellites} satellites"
    )
    if target is None:
        print(
            "no daemon to tell (--config or --daemon): no survey opened; "
            "open one with `seamap ctl start`"
        )
        return 0
    answer = request.request_survey_start(target, timeout_s=min(args.timeout, 10.0), area=plan.area)
    if answer.survey is not None:
        covering = " (covering the plan's area)" if plan.area is not None else ""
        print(f"survey {answer.survey} recording on {target.vehicle}{covering}")
        return 0
    # The boat is under way: undoing the mission would leave it holding on the water, and
    # a survey can still be opened by hand; so say so and let it run.
    print(
        f"seamap survey: the mission runs, but no survey was opened: {answer.problem}; "
        "open one with `seamap ctl start`",
        file=sys.stderr,
    )
    return 1


def run_steer(args: argparse.Namespace) -> int:
    import asyncio

    from drivers import mission

    _check_timeout(args)
    url = mission.mavsdk_url(args.connect)
    if args.survey_command == "status":
        status = asyncio.run(mission.mission_status(url, args.timeout))
        if args.json:
            print(json.dumps(status.as_dict(), sort_keys=True))
        else:
            print(format_status(status.as_dict()))
        return 0
    steer = {
        "pause": (mission.pause_survey, "holding (HOLD)"),
        "resume": (mission.resume_survey, "mission continues (AUTO)"),
        "abort": (mission.abort_survey, "returning to launch (RTL)"),
    }
    step, done = steer[args.survey_command]
    asyncio.run(step(url, args.timeout))
    print(done)
    return 0


def format_status(status: dict[str, Any]) -> str:
    total = status["total"]
    item = f"item {status['current']} of {total if total is not None else '?'}"
    if status["fraction"] is not None:
        item += f" ({100 * status['fraction']:.0f} %)"
    parts = [item]
    if status["state"]:
        parts.append(f"mission {status['state']}")
    parts.append(f"{status['flight_mode']} mode")
    parts.append("armed" if status["armed"] else "disarmed")
    return ", ".join(parts)
