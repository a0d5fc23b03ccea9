"""The autopilot link silent mid-survey: how the live map and the survey-end pass carry the
boat through on the sonar alone (issue 13, item 1).

For each survey of the matrix named (``tools.accuracy.SURVEYS``) and each place chosen, every
record of the simulated autopilot log in a window of ``--gap`` seconds is dropped (what the
daemon records when the MAVLink link is cut: nothing at all, no IMU, no GNSS, no heading),
the logs are fed to the streaming engine in arrival order as the daemon feeds it, and the
pings of the window are compared with the simulator's truth, for the live map (the poses as
they stood before the survey-end pass) and for the survey-end pass:

- posed: the window's pings given a pose, of all pings in it;
- heading error (grid heading against the truth's), median and largest; and the heading's
  drift: how far that error moved from what it was over the 5 s before the window (the
  absolute heading of a fused survey is itself 1-3 degrees off the truth on these field
  days: the compass's misalignment is observable only through the GNSS track);
- drift: how far the position error moved from what it was over the 5 s before the window
  (the GNSS's own bias is common to both and cancels), median and largest; and the
  shape error: the same against the error drawn in a straight line from what it was over
  the 5 s before the window to what it is over the 5 s after (the GNSS's bias wanders by
  decimetres in 30 s: a map tied to it on both sides of the silence moves with it, which
  is right, and the shape error is what is left: the chain's);
- the same over the 20 s after the window: the recovery.

Places: ``turn`` (the window holding the largest turn: a lawnmower U-turn), ``turn1`` (the
next such window), ``mid`` (the survey's middle), ``start`` (3 s after the first ping).

    python -m tools.navloss --out DIR [--surveys NAME ...] [--where turn mid ...]
                            [--gap 30] [--jobs 2]

Writes ``DIR/navloss.json`` and prints a table. Slow (a minute or two a case on one core):
``make navloss``, not CI.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import struct
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from drivers.mavlink.framing import scan_tlog
from drivers.mavlink.navlog import NavReadReport
from tools.accuracy import SURVEYS, Survey
from tools.sim import simulate

DEFAULT_SURVEYS = (
    "quadrats-s1",
    "quadrats-s4",
    "quadrats-s5-2hz",
    "quadrats-s7-10hz",
    "quadrats-s1-px4",
    "quadrats-current-s3-2hz",
    "farm-s1-300s",
)
PLACES = ("turn", "turn1", "mid", "start")


def cut_tlog(src: Path, dst: Path, t0: float, t1: float) -> int:
    """Copy a tlog without its records stamped in [t0, t1); returns how many were dropped."""
    out = bytearray()
    dropped = 0
    for stamp, msg in scan_tlog(src.read_bytes(), NavReadReport(str(src), "tlog")):
        if t0 <= stamp < t1:
            dropped += 1
            continue
        out += struct.pack(">Q", round(stamp * 1e6)) + bytes(msg.get_msgbuf())
    dst.write_bytes(bytes(out))
    return dropped


def window_start(pings: Sequence[dict[str, Any]], gap: float, where: str) -> float:
    """Survey time at which the silence starts, for ``where`` (see the module's doc)."""
    times = np.array([p["time"] for p in pings], float)
    first, last = float(times[0]), float(times[-1])
    if where == "start":
        return first + 3.0
    if where == "mid":
        return first + 0.5 * (last - first) - 0.5 * gap
    if not where.startswith("turn"):
        raise ValueError(f"navloss: unknown place {where!r}")
    heading = np.unwrap(np.radians([p["grid_heading_deg"] for p in pings]))
    rank = int(where[4:] or 0)
    candidates = []
    for k, t in enumerate(times):
        if t < first + 5.0 or t + gap > last - 5.0:
            continue
        j = min(int(np.searchsorted(times, t + gap)), times.size - 1)
        candidates.append((abs(float(heading[j] - heading[k])), float(t)))
    candidates.sort(reverse=True)
    chosen: list[float] = []
    for _, t in candidates:
        if all(abs(t - c) > gap for c in chosen):
            chosen.append(t)
        if len(chosen) > rank:
            return chosen[rank]
    raise ValueError(f"navloss: the survey has no window {where!r} of {gap:g} s")


def measure(
    times: np.ndarray,
    poses_utm: np.ndarray,
    pings: Sequence[dict[str, Any]],
    t0: float,
    t1: float,
    after_s: float = 20.0,
) -> dict[str, Any]:
    """Posed fraction, heading error and drift of the window's pings and of the ``after_s``
    after it. ``poses_utm``: (n, 3) east, north (m), grid heading (rad); NaN: not posed."""

    def pose_at(ping: dict[str, Any]) -> np.ndarray | None:
        if times.size == 0:
            return None
        i = int(np.argmin(np.abs(times - ping["time"])))
        if abs(times[i] - ping["time"]) > 1e-3 or not np.all(np.isfinite(poses_utm[i])):
            return None
        return poses_utm[i]

    def heading_error(q: np.ndarray, ping: dict[str, Any]) -> float:
        turn = math.degrees(q[2]) - ping["grid_heading_deg"]
        return (turn + 180.0) % 360.0 - 180.0

    before, before_heading = [], []
    for ping in pings:
        if t0 - 5.0 <= ping["time"] < t0 and (q := pose_at(ping)) is not None:
            before.append((q[0] - ping["east"], q[1] - ping["north"]))
            before_heading.append(heading_error(q, ping))
    offset = np.mean(before, axis=0) if before else np.zeros(2)
    heading_offset = float(np.mean(before_heading)) if before_heading else 0.0
    after = []
    for ping in pings:
        if t1 <= ping["time"] < t1 + 5.0 and (q := pose_at(ping)) is not None:
            after.append((q[0] - ping["east"], q[1] - ping["north"]))
    offset_after = np.mean(after, axis=0) if after else offset
    out: dict[str, Any] = {}
    for name, lo, hi in (("gap", t0, t1), ("after", t1, t1 + after_s)):
        group = [p for p in pings if lo <= p["time"] < hi]
        drift, heading, turned, shape = [], [], [], []
        for ping in group:
            if (q := pose_at(ping)) is None:
                continue
            error = np.array([q[0] - ping["east"], q[1] - ping["north"]]) - offset
            drift.append(float(np.hypot(*error)))
            w = min(max((ping["time"] - t0) / max(t1 - t0, 1e-9), 0.0), 1.0)
            shape.append(float(np.hypot(*(error - w * (offset_after - offset)))))
            heading.append(abs(heading_error(q, ping)))
            turned.append(abs(heading_error(q, ping) - heading_offset))
        entry: dict[str, Any] = {"pings": len(group), "posed": len(drift)}
        if drift:
            entry.update(
                drift_median_m=round(float(np.median(drift)), 3),
                drift_max_m=round(float(np.max(drift)), 3),
                heading_median_deg=round(float(np.median(heading)), 2),
                heading_max_deg=round(float(np.max(heading)), 2),
                heading_drift_median_deg=round(float(np.median(turned)), 2),
                heading_drift_max_deg=round(float(np.max(turned)), 2),
                shape_median_m=round(float(np.median(shape)), 3),
                shape_max_m=round(float(np.max(shape)), 3),
            )
        out[name] = entry
    out["heading_before_deg"] = round(heading_offset, 2)
    out["offset_change_m"] = round(float(np.hypot(*(offset_after - offset))), 3)
    return out


def run_case(row: Survey, where: str, gap: float, out: Path) -> dict[str, Any]:
    """One survey, one silence: the live map and the survey-end pass measured."""
    from daemon.config import load_config
    from daemon.replay import (
        mount_from_config,
        ping_source,
        pipeline_params,
        read_navigation,
        stream_survey,
    )
    from mapping.pipeline import SurveyResult

    sim = out / "sims" / row.name
    if not (sim / "truth.json").exists():
        simulate(row.scenario, row.seed, sim, **row.overrides)
    truth = json.loads((sim / "truth.json").read_text())
    pings = truth["pings"]
    t0 = window_start(pings, gap, where)
    case = out / "cases" / f"{row.name}-{where}-{gap:g}s"
    case.mkdir(parents=True, exist_ok=True)
    dropped = cut_tlog(sim / "nav.tlog", case / "nav.tlog", t0, t0 + gap)
    config = load_config(sim / "site.toml")
    samples, _ = read_navigation([case / "nav.tlog"], config)
    started = time.perf_counter()
    final, (live, stats) = stream_survey(
        ping_source([sim / "sonar.oculus"], {}),
        samples,
        mount_from_config(config.sonar),
        pipeline_params(config),
    )

    def utm(result: SurveyResult) -> np.ndarray:
        east, north = result.frame.to_utm(result.poses[:, 0], result.poses[:, 1])
        return np.column_stack([east, north, result.poses[:, 2]])

    return {
        "survey": row.name,
        "where": where,
        "gap_s": gap,
        "start_s": round(t0 - pings[0]["time"], 2),
        "records_dropped": dropped,
        "live": measure(np.asarray(live.times), utm(live), pings, t0, t0 + gap),
        "final": measure(np.asarray(final.times), utm(final), pings, t0, t0 + gap),
        "rejected_live": dict(stats.rejected),
        "rejected_final": dict(final.rejected),
        "seconds": round(time.perf_counter() - started, 1),
    }


def _case(args: tuple[Survey, str, float, Path]) -> dict[str, Any]:
    try:
        return run_case(*args)
    except Exception as exc:  # one case failing must not lose the others
        row, where, gap, _ = args
        return {"survey": row.name, "where": where, "gap_s": gap, "error": repr(exc)}


def _fmt(entry: dict[str, Any]) -> str:
    if "drift_max_m" not in entry:
        return f"{entry.get('posed', 0)}/{entry.get('pings', 0)} posed"
    return (
        f"{entry['posed']}/{entry['pings']} posed, heading {entry['heading_median_deg']:.1f}"
        f"/{entry['heading_max_deg']:.1f} (drift {entry['heading_drift_median_deg']:.1f}"
        f"/{entry['heading_drift_max_deg']:.1f}) deg, drift {entry['drift_median_m']:.2f}"
        f"/{entry['drift_max_m']:.2f} (shape {entry['shape_median_m']:.2f}"
        f"/{entry['shape_max_m']:.2f}) m"
    )


def table(results: Sequence[dict[str, Any]]) -> str:
    lines = []
    for r in results:
        head = f"{r['survey']} {r['where']} {r['gap_s']:g}s"
        if "error" in r:
            lines.append(f"{head}: ERROR {r['error']}")
            continue
        for part in ("live", "final"):
            lines.append(
                f"{head} {part:5s}: gap {_fmt(r[part]['gap'])}; after {_fmt(r[part]['after'])}"
            )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.navloss", description=__doc__)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--surveys", nargs="+", default=list(DEFAULT_SURVEYS))
    parser.add_argument("--where", nargs="+", default=list(PLACES))
    parser.add_argument("--gap", type=float, nargs="+", default=[30.0])
    parser.add_argument("--jobs", type=int, default=1)
    args = parser.parse_args(argv)
    known = {row.name: row for row in SURVEYS}
    unknown = [name for name in args.surveys if name not in known]
    if unknown:
        print(f"navloss: unknown survey(s) {', '.join(unknown)}", file=sys.stderr)
        return 2
    cases = [
        (known[name], where, gap, args.out)
        for name in args.surveys
        for gap in args.gap
        for where in args.where
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    results: list[dict[str, Any]] = []
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for result in pool.map(_case, cases):
            results.append(result)
            print(table([result]), flush=True)
            (args.out / "navloss.json").write_text(json.dumps(results, indent=1))
    print(table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
