"""The accuracy matrix's files: ``matrix.json`` (every number) and ``matrix.md`` (tables).

``matrix_document`` summarises the surveys' entries (``tools.accuracy.run_survey``): per
metric and mode, the median and the worst over the surveys that have it. ``matrix.md``
has one table per metric (modes down, median and worst across) and one table of the
surveys (a few headline numbers per mode). NaN is written as JSON null.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class Metric:
    """A column of the matrix: its key in a mode's numbers, a title, the unit it is shown
    in (``scale`` times the stored SI value) and whether larger is worse."""

    key: str
    title: str
    unit: str
    scale: float = 1.0
    larger_is_worse: bool = True
    digits: int = 1


METRICS: tuple[Metric, ...] = (
    Metric("lanes_rms_m", "Lane disagreement, RMS", "cm", 100.0),
    Metric("lanes_median_m", "Lane disagreement, median", "cm", 100.0),
    Metric("lanes_p90_m", "Lane disagreement, p90", "cm", 100.0),
    Metric("live_lanes_rms_m", "Live map lane disagreement, RMS (streaming)", "cm", 100.0),
    Metric("live_lanes_median_m", "Live map lane disagreement, median (streaming)", "cm", 100.0),
    Metric("live_lanes_p90_m", "Live map lane disagreement, p90 (streaming)", "cm", 100.0),
    Metric("spacing_rmse_m", "Quadrat spacing RMSE within arrays", "cm", 100.0),
    Metric("spacing_all_rmse_m", "Quadrat spacing RMSE over all pairs", "cm", 100.0),
    Metric("array_offset_max_m", "Array offset (georeferencing), largest array", "m", 1.0, True, 2),
    Metric("rpe_10s_m", "Relative pose error over 10 s, translation RMS", "cm", 100.0),
    Metric("rpe_10s_deg", "Relative pose error over 10 s, yaw RMS", "deg", 1.0, True, 2),
    Metric("ate_m", "Absolute trajectory error, RMS", "m", 1.0, True, 3),
    Metric("ate_aligned_m", "Absolute trajectory error after rigid alignment", "cm", 100.0),
    Metric("mapped_fraction", "Frames mapped / read", "%", 100.0, False),
    Metric("seconds_per_frame", "Replay time per frame read", "ms", 1000.0, True, 0),
)


def _finite(values: Sequence[Any]) -> list[float]:
    return [float(v) for v in values if isinstance(v, int | float) and math.isfinite(v)]


def _median(values: list[float]) -> float:
    ordered = sorted(values)
    mid = len(ordered) // 2
    return ordered[mid] if len(ordered) % 2 else (ordered[mid - 1] + ordered[mid]) / 2


def summary(entries: Sequence[dict[str, Any]], modes: Sequence[str]) -> dict[str, Any]:
    """Per metric, per mode: median, worst and the number of surveys with a value."""
    out: dict[str, Any] = {}
    for metric in METRICS:
        per_mode: dict[str, Any] = {}
        for mode in modes:
            values = _finite([e.get("modes", {}).get(mode, {}).get(metric.key) for e in entries])
            if not values:
                continue
            worst = max(values) if metric.larger_is_worse else min(values)
            per_mode[mode] = {"median": _median(values), "worst": worst, "surveys": len(values)}
        if per_mode:
            out[metric.key] = per_mode
    return out


def matrix_document(
    entries: Sequence[dict[str, Any]], modes: Sequence[str], elapsed_s: float
) -> dict[str, Any]:
    """matrix.json's content."""
    return {
        "format": "seamap-accuracy-matrix",
        "version": 1,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "elapsed_s": round(elapsed_s, 1),
        "modes": list(modes),
        "metrics": {m.key: m.title for m in METRICS},
        "summary": summary(entries, modes),
        "surveys": list(entries),
    }


def _nan_to_none(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _cell(metric: Metric, value: Any) -> str:
    if not isinstance(value, int | float) or not math.isfinite(value):
        return "–"
    return f"{value * metric.scale:.{metric.digits}f}"


HEADLINE = ("lanes_rms_m", "spacing_rmse_m", "rpe_10s_m", "ate_m")


def render_markdown(document: dict[str, Any]) -> str:
    """matrix.md: one table per metric, then the surveys."""
    modes: list[str] = document["modes"]
    entries: list[dict[str, Any]] = document["surveys"]
    scored = [e for e in entries if "error" not in e]
    lines = [
        "# Accuracy matrix",
        "",
        f"{len(scored)} surveys scored, {len(entries) - len(scored)} skipped, "
        f"modes {', '.join(modes)}; {document['elapsed_s']:.0f} s; {document['created']}.",
        "",
        "Lane disagreement: how far apart two passes over the same seabed point draw it "
        "(the true fans say which frames saw it, the estimated poses where they put it). "
        "Quadrat spacing: within each array, blind to where the array sits; array offset: "
        "where it sits (the georeferencing error).",
        "",
    ]
    for e in entries:
        if "error" in e:
            lines.append(f"- skipped {e['name']}: {e['error']}")
        for mode, numbers in e.get("modes", {}).items():
            if "error" in numbers:
                lines.append(f"- {e['name']} {mode} failed: {numbers['error']}")
    lines.append("")
    for metric in METRICS:
        per_mode = document["summary"].get(metric.key)
        if not per_mode:
            continue
        worst = "worst (largest)" if metric.larger_is_worse else "worst (smallest)"
        lines += [f"## {metric.title} ({metric.unit})", ""]
        lines += [f"| mode | median | {worst} | surveys |", "| --- | ---: | ---: | ---: |"]
        for mode in modes:
            if mode in per_mode:
                s = per_mode[mode]
                lines.append(
                    f"| {mode} | {_cell(metric, s['median'])} | {_cell(metric, s['worst'])} "
                    f"| {s['surveys']} |"
                )
        lines.append("")
    headline = [m for m in METRICS if m.key in HEADLINE]
    lines += [
        "## Surveys",
        "",
        "Each cell: "
        + " / ".join(f"{m.title.split(',')[0].lower()} ({m.unit})" for m in headline)
        + "; frames mapped of read.",
        "",
        "| survey | pings | " + " | ".join(modes) + " |",
        "| --- | ---: | " + " | ".join("---" for _ in modes) + " |",
    ]
    for e in entries:
        pings = e.get("simulation", {}).get("pings", "–")
        cells = []
        for mode in modes:
            numbers = e.get("modes", {}).get(mode)
            if numbers is None:
                cells.append("–")
            elif "error" in numbers:
                cells.append("failed")
            else:
                values = " / ".join(_cell(m, numbers.get(m.key)) for m in headline)
                read, mapped = numbers.get("frames_read"), numbers.get("frames_mapped")
                count = (
                    f"{mapped:.0f}/{read:.0f}" if read is not None and mapped is not None else ""
                )
                cells.append(f"{values}; {count}")
        if "error" in e:
            cells = ["skipped"] * len(modes)
        lines.append(f"| {e['name']} | {pings} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_matrix(out: Path, document: dict[str, Any]) -> None:
    """Write matrix.json and matrix.md into ``out`` (each replaced atomically)."""
    clean = _nan_to_none(document)
    for name, text in (
        ("matrix.json", json.dumps(clean, indent=1, sort_keys=False) + "\n"),
        ("matrix.md", render_markdown(document)),
    ):
        partial = out / f".{name}.partial"
        partial.write_text(text, encoding="utf-8")
        os.replace(partial, out / name)
