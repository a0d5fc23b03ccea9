"""``seamap evaluate``: the paper's whole evaluation on one survey, into a report folder.

Steps (each said on the terminal as it starts, with its seconds when done):

1. Table I over every ``every``-th frame and its successor (``preprocessing``);
2. the four mapping modes, each a ``seamap replay`` into ``OUT/modes/{mode}/``;
3. Table II over every pair of consecutive pings: the baselines' and FMT's pairwise
   registrations and the modes' steps (``registration``), and with a truth each
   method's ATE, RPE and lane disagreement;
4. Table III from the modes and Table IV from single-stage replays at each lambda
   (``modes``; lambda 1e4 is the single-stage run itself);
5. Table V: the single-stage trajectory rendered with each blending (``blending``);
6. the figures and ``report.md`` / ``tables.json`` (``report``).
"""

from __future__ import annotations

import itertools
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from daemon.config import SiteConfig, load_config
from daemon.replay import (
    check_captures,
    mount_from_config,
    ping_source,
    pipeline_params,
    read_navigation,
)
from drivers.errors import SeamapError
from mapping.coverage import SonarFan
from mapping.frames import LocalRegistration
from tools.evaluation import blending, figures, modes, registration
from tools.evaluation.baselines import REGISTRATION_BASELINES
from tools.evaluation.metrics import Quadrat
from tools.evaluation.preprocessing import CONFIGURATIONS, preprocessing_table
from tools.evaluation.reference import SonarSetup
from tools.evaluation.report import write_report
from tools.evaluation.truth import replay_altitude

Say = Callable[[str], None]


@dataclass(frozen=True)
class Inputs:
    """What is evaluated: the survey's logs (segments in order), its config, and what is
    known of its truth (a simulator's truth.json or a reference trajectory CSV, matched to
    the frames with ``truth_matching``: ``tolerance_s``, ``max_gap_s``)."""

    sonar: list[Path]
    nav: list[Path]
    config: SiteConfig
    config_path: Path | None
    truth: Path | None
    quadrats_path: Path | None
    name: str
    truth_matching: dict[str, Any] = field(default_factory=dict)


def resolve_inputs(
    survey: Path | None,
    sonar: list[Path] | None,
    nav: list[Path] | None,
    config_path: Path | None,
    truth: Path | None,
    quadrats: Path | None,
    truth_matching: dict[str, Any] | None = None,
) -> Inputs:
    """The logs of a survey folder (a simulator's ``sonar.oculus`` + ``nav.tlog``, or a
    daemon's ``sonar-NNN.oculus`` + ``nav-NNN.tlog`` segments) or those given; the config
    given, else the folder's ``site.toml``, else the defaults; the truth given, else a
    simulator folder's ``truth.json`` (a truth given may be a reference trajectory CSV,
    ``tools.evaluation.reference``). SeamapError (one line) for what is missing or
    malformed."""
    if survey is not None:
        if not survey.is_dir():
            raise SeamapError(f"{survey}: no such survey folder")
        segments = sorted(survey.glob("sonar-*.oculus"))
        if segments:
            sonar, nav = segments, sorted(survey.glob("nav-*.tlog"))
        else:
            sonar, nav = [survey / "sonar.oculus"], [survey / "nav.tlog"]
        if config_path is None and (survey / "site.toml").is_file():
            config_path = survey / "site.toml"
        if truth is None and (survey / "truth.json").is_file() and not segments:
            truth = survey / "truth.json"
        name = survey.name
    else:
        if not sonar or not nav:
            raise SeamapError("give a survey folder, or --sonar and --nav")
        name = sonar[0].stem
    for log in [*sonar, *nav]:
        if not log.is_file():
            raise SeamapError(f"{log}: no such file")
    for given in (truth, quadrats):
        if given is not None and not given.is_file():
            raise SeamapError(f"{given}: no such file")
    matching = dict(truth_matching or {})
    if truth is not None:
        from tools.evaluation.truth import load_reference

        load_reference(truth, **matching)  # a file that is no reference says so now
    config = load_config(config_path)
    return Inputs(list(sonar), list(nav), config, config_path, truth, quadrats, name, matching)


def evaluate_survey(inputs: Inputs, out: Path, every: int = 10, say: Say = print) -> dict[str, Any]:
    """Run the evaluation (module doc) into ``out``; returns tables.json's content."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SeamapError(f"{out}: cannot create the report folder ({exc.strerror})") from None
    config = inputs.config
    mount = mount_from_config(config.sonar)
    skipped: dict[str, int] = {}
    pings = ping_source(inputs.sonar, skipped)
    nav, _ = read_navigation(inputs.nav, config)
    check_captures(inputs.sonar, None, "seamap replay --sonar-start maps one; evaluate takes logs")
    times = [float(p.time) for p in pings()]
    if len(times) < 3:
        raise SeamapError(f"{inputs.sonar[0]}: too few sonar pings to evaluate ({len(times)})")
    tables: dict[str, Any] = {
        "survey": inputs.name,
        "inputs": {
            "sonar": [str(p) for p in inputs.sonar],
            "nav": [str(p) for p in inputs.nav],
            "config": str(inputs.config_path) if inputs.config_path else None,
            "truth": str(inputs.truth) if inputs.truth else None,
            "quadrats": str(inputs.quadrats_path) if inputs.quadrats_path else None,
        },
        "frames": len(times),
    }
    step = _Steps(say)

    step.start(1, f"Table I: the {len(CONFIGURATIONS)} preprocessings over every {every}th frame")
    tables["table_i"] = preprocessing_table(pings, mount, every)
    step.done()

    runs: dict[str, modes.ModeRun] = {}
    for k, mode in enumerate(modes.MODES):
        step.start(2, f"mapping {mode} ({k + 1}/{len(modes.MODES)})")
        runs[mode] = modes.run_mode(
            inputs.sonar, inputs.nav, config, mode, out / "modes" / mode, inputs.truth,
            truth_matching=inputs.truth_matching,
        )  # fmt: skip
        step.done(f"{runs[mode].report['frames']['mapped']} of {len(times)} frames mapped")
    epsg = runs["single-stage"].epsg
    quadrats = _quadrats(inputs, epsg)

    step.start(3, f"Table II: {len(times) - 1} consecutive pairs, FMT and "
                  f"{', '.join(REGISTRATION_BASELINES)}")  # fmt: skip
    tables["table_ii"] = _table_ii(inputs, pings, times, runs, epsg, mount)
    step.done(", ".join(
        f"{m} {row['ms_per_pair']:.0f} ms/pair" for m, row in tables["table_ii"]["pairwise"].items()
    ))  # fmt: skip

    step.start(4, "Table III from the modes; Table IV: single-stage at lambda 1e2 ... 1e6")
    tables["table_iii"] = {
        mode: _spacing(modes.quadrat_spacing(run, quadrats)) for mode, run in runs.items()
    }
    tables["table_iv"] = _table_iv(inputs, runs, quadrats, epsg, out, times)
    step.done()

    step.start(5, "Table V: the single-stage trajectory rendered with each blending")
    trajectory = registration.read_trajectory(runs["single-stage"].folder / "trajectory.csv", epsg)
    params = pipeline_params(config)
    rendered = {
        method: blending.render_trajectory(pings, times, trajectory, mount, params, nav, method)
        for method in blending.BLENDINGS
    }
    tables["table_v"] = blending.blending_table(rendered)
    step.done()

    step.start(6, "figures and report")
    figure_files = _figures(out, pings, len(times), mount, runs, rendered, quadrats, every)
    tables["figures"] = figure_files
    tables["modes"] = {mode: _mode_summary(run) for mode, run in runs.items()}
    (out / "tables.json").write_text(json.dumps(_finite(tables), indent=1) + "\n")
    write_report(out / "report.md", tables)
    step.done()
    return tables


class _Steps:
    def __init__(self, say: Say) -> None:
        self.say = say
        self.started = time.perf_counter()

    def start(self, n: int, text: str) -> None:
        self.started = time.perf_counter()
        self.say(f"[{n}/6] {text}")

    def done(self, extra: str = "") -> None:
        seconds = time.perf_counter() - self.started
        self.say(f"      done in {seconds:.1f} s" + (f": {extra}" if extra else ""))


def _quadrats(inputs: Inputs, epsg: int) -> list[Quadrat] | None:
    if inputs.quadrats_path is not None:
        return modes.read_quadrats(inputs.quadrats_path, epsg)
    if inputs.truth is not None:
        from tools.evaluation.truth import load_reference

        return load_reference(inputs.truth, **inputs.truth_matching).quadrats() or None
    return None


def _spacing(spacing: dict[str, Any] | None) -> dict[str, Any] | None:
    if spacing is None:
        return None
    keys = ("mae", "rmse", "pairs", "located", "all_mae", "all_rmse")
    return {k: spacing[k] for k in keys if k in spacing}


def _table_ii(
    inputs: Inputs,
    pings: Any,
    times: list[float],
    runs: dict[str, modes.ModeRun],
    epsg: int,
    mount: Any,
) -> dict[str, Any]:
    pairs = list(itertools.pairwise(times))
    trajectories = {
        mode: registration.read_trajectory(run.folder / "trajectory.csv", epsg)
        for mode, run in runs.items()
    }
    steps = {mode: registration.trajectory_steps(t, pairs) for mode, t in trajectories.items()}
    params = pipeline_params(inputs.config)
    pairwise = registration.pairwise_steps(
        pings, mount, pairs, preprocess=params.preprocess, fmt_params=params.fmt
    )
    references = {"fmt-only": steps["fmt-only"], "gps-only": steps["gps-only"]}
    rows: dict[str, Any] = {}
    for method, found in pairwise.items():
        if method == "fmt":
            continue
        rows[method] = {
            f"vs_{ref}": registration.consistency(found.steps, reference)
            for ref, reference in references.items()
        }
        rows[method]["failed"] = found.failed
    for mode in ("fmt-only", "gps-only", "single-stage", "two-stage"):
        rows[mode] = {
            f"vs_{ref}": registration.consistency(steps[mode], reference)
            for ref, reference in references.items()
            if ref != mode
        }
    section: dict[str, Any] = {
        "pairs": len(pairs),
        "rows": rows,
        "pairwise": {
            method: {"ms_per_pair": found.ms_per_pair, "failed": found.failed}
            for method, found in pairwise.items()
        },
    }
    if inputs.truth is not None:
        # The altitude single-stage's replay used, so that the baselines' lanes are
        # scored with the heads the modes' were.
        altitude = replay_altitude(
            runs["single-stage"].report.get("bottom", {}), inputs.config.sonar.altitude_m
        )
        sonar = SonarSetup(
            mount, SonarFan.of_ping(next(iter(pings())), mount, params.preprocess), altitude
        )
        section["truth"], section["reference"] = _with_truth(
            inputs, times, pairwise, trajectories, runs, epsg, sonar
        )
    return section


def _with_truth(
    inputs: Inputs,
    times: list[float],
    pairwise: dict[str, registration.PairwiseSteps],
    trajectories: dict[str, registration.Trajectory],
    runs: dict[str, modes.ModeRun],
    epsg: int,
    sonar: SonarSetup,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Each method's ATE, RPE over 10 s and lane disagreement against the truth (or the
    reference trajectory: its heads and fan from ``sonar``): the modes' from their
    reports, the baselines' from their chained steps; and how the frames met the
    reference (``Matched.summary``, with what it cannot score)."""
    from tools.evaluation.truth import load_reference, trajectory_section
    from tools.lanes import lane_disagreement

    assert inputs.truth is not None
    source = load_reference(inputs.truth, **inputs.truth_matching)
    stamps = np.asarray(times, float)
    matched = source.at(stamps, epsg, sonar)
    true, heads, fan = matched.poses, matched.heads, matched.fan
    centres = np.array([(q.east, q.north) for q in source.quadrats()], float).reshape(-1, 2)
    gps = trajectories["gps-only"].by_time()
    reference = np.array([gps.get(round(t, 4), (np.nan,) * 3) for t in times], float)
    out: dict[str, Any] = {}
    for mode, run in runs.items():
        accuracy = run.report.get("accuracy", {})
        trajectory, lanes = accuracy.get("trajectory", {}), accuracy.get("lanes", {})
        out[mode] = _truth_row(trajectory, lanes)
    for method, found in pairwise.items():
        name = "fmt-pairwise" if method == "fmt" else method
        est = registration.chained(found.steps, reference)
        lanes = lane_disagreement(stamps, true, est, heads, fan, centres)
        out[name] = _truth_row(trajectory_section(stamps, est, true), lanes)
    summary = dict(matched.summary)
    if source.unavailable:
        summary["unavailable"] = source.unavailable
    return out, summary


def _truth_row(trajectory: dict[str, Any], lanes: dict[str, Any]) -> dict[str, Any]:
    return {
        "ate_m": trajectory.get("rmse"),
        "ate_aligned_m": trajectory.get("aligned_rmse"),
        "rpe_10s_m": trajectory.get("rpe_10s_m"),
        "lanes_rms_m": lanes.get("rms_m"),
        "lanes_median_m": lanes.get("median_m"),
    }


def _table_iv(
    inputs: Inputs,
    runs: dict[str, modes.ModeRun],
    quadrats: list[Quadrat] | None,
    epsg: int,
    out: Path,
    times: list[float],
) -> dict[str, Any]:
    pairs = list(itertools.pairwise(times))  # Table II's: consecutive pings
    references = {
        ref: registration.trajectory_steps(
            registration.read_trajectory(runs[ref].folder / "trajectory.csv", epsg), pairs
        )
        for ref in ("fmt-only", "gps-only")
    }
    rows: dict[str, Any] = {}
    for lam in modes.LAMBDAS:
        if lam == 1e4:
            run = runs["single-stage"]
        else:
            run = modes.run_mode(
                inputs.sonar, inputs.nav, inputs.config, "single-stage",
                out / "lambda" / f"{lam:.0e}", inputs.truth,
                params=modes.lambda_params(inputs.config, lam),
                truth_matching=inputs.truth_matching,
            )  # fmt: skip
        trajectory = registration.read_trajectory(run.folder / "trajectory.csv", epsg)
        steps = registration.trajectory_steps(trajectory, pairs)
        row: dict[str, Any] = {
            "spacing": _spacing(modes.quadrat_spacing(run, quadrats)),
            **{f"vs_{ref}": registration.consistency(steps, r) for ref, r in references.items()},
        }
        accuracy = run.report.get("accuracy", {}).get("trajectory")
        if accuracy:
            row["ate_aligned_m"] = accuracy.get("aligned_rmse")
        rows[f"{lam:.0e}"] = row
    return {"alpha": modes.ALPHA, "rows": rows}


def _mode_summary(run: modes.ModeRun) -> dict[str, Any]:
    frames = run.report["frames"]
    return {
        "folder": str(run.folder),
        "frames_mapped": frames["mapped"],
        "frames_read": frames["read"],
        "seconds": run.report.get("timings_s", {}).get("total"),
    }


def _figures(
    out: Path,
    pings: Any,
    count: int,
    mount: Any,
    runs: dict[str, modes.ModeRun],
    rendered: dict[str, blending.Rendered],
    quadrats: list[Quadrat] | None,
    every: int,
) -> list[str]:
    boxes = quadrats or []
    panels = []
    for mode in ("fmt-only", "single-stage", "two-stage"):
        image, west, north, res = figures.read_mosaic(runs[mode].folder / "mosaic.tif")
        panels.append((mode, image, west, north, res))
    figures.mosaics_figure(out / "fig4_modes.png", panels, boxes,
                           "Fig. 4: the mapping modes (quadrats boxed where known)")  # fmt: skip
    figures.mosaics_figure(
        out / "fig5_blending.png",
        [
            (blending.BLENDING_NAMES[m], r.image, r.west, r.north, r.res_m)
            for m, r in rendered.items()
        ],
        boxes,
        "Fig. 5: the blendings on the single-stage poses",
    )
    # Fig. 3: the survey's middle sampled frame under each preprocessing.
    wanted = (count // 2) // every * every
    ping = next(p for k, p in enumerate(pings()) if k == wanted)
    strip = []
    for configuration in CONFIGURATIONS:
        frame = LocalRegistration(mount, configuration.params).frame(ping)
        strip.append((configuration.name, frame.image, frame.mask))
    figures.preprocessing_figure(out / "fig3_preprocessing.png", strip)
    return ["fig3_preprocessing.png", "fig4_modes.png", "fig5_blending.png"]


def _finite(value: Any) -> Any:
    """JSON without NaN: NaN and infinities become null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, np.floating | np.integer):
        return _finite(value.item())
    return value
