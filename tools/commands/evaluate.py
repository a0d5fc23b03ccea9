"""``seamap evaluate``: the paper's evaluation (Tables I-V, Figs. 3-5) on one survey."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from seamap.commands.replay import add_truth_matching


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="the paper's evaluation on a survey: Tables I-V and figures into a report folder",
        description=(
            "Run the paper's comparisons on one survey: the preprocessing ablation (Table "
            "I), the registration baselines ORB, SIFT and ECC against FMT and the mapping "
            "modes (Table II), quadrat spacing (Table III), the lambda ablation (Table "
            "IV) and the blendings (Table V), with Figs. 3-5; report.md, tables.json and "
            "the figures go into --out."
        ),
    )
    parser.add_argument(
        "survey",
        nargs="?",
        type=Path,
        metavar="SURVEY_DIR",
        help="a simulator folder (sonar.oculus, nav.tlog, site.toml, truth.json) or a "
        "daemon survey folder (sonar-NNN.oculus, nav-NNN.tlog)",
    )
    parser.add_argument("--sonar", type=Path, action="append", help="Oculus log (repeatable)")
    parser.add_argument("--nav", type=Path, action="append", help="MAVLink log (repeatable)")
    parser.add_argument("--config", type=Path, help="site TOML (default: the folder's site.toml)")
    parser.add_argument(
        "--truth",
        type=Path,
        help=(
            "a simulator's truth.json (default: the folder's), or a reference trajectory "
            "CSV (RTK+INS, total station: columns time,lat,lon,heading_deg, optional "
            "east,north, roll_deg,pitch_deg, altitude_m; told apart by content)"
        ),
    )
    add_truth_matching(parser)
    parser.add_argument(
        "--quadrats",
        type=Path,
        help='taped quadrats, JSON {"quadrats": [{"lat", "lon", "side_m", ...}]}',
    )
    parser.add_argument(
        "--every", type=int, default=10, help="Table I samples every Nth frame (%(default)s)"
    )
    parser.add_argument("--out", type=Path, required=True, help="the report folder")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from drivers.errors import SeamapError
    from seamap.commands.replay import truth_matching
    from tools.evaluation.run import evaluate_survey, resolve_inputs

    if args.survey is not None and (args.sonar or args.nav):
        raise SeamapError("give a survey folder or --sonar and --nav, not both")
    if args.every < 1:
        raise SeamapError(f"--every {args.every}: must be 1 or more")
    inputs = resolve_inputs(
        args.survey, args.sonar, args.nav, args.config, args.truth, args.quadrats,
        truth_matching(args),
    )  # fmt: skip
    evaluate_survey(inputs, args.out, args.every, say=lambda text: print(text, flush=True))
    print(f"report: {args.out / 'report.md'} (tables.json, fig3-5 PNG)")
    return 0
