"""report.md: the evaluation's tables, ours beside the paper's published numbers.

Each table has the paper's columns; where we measure more (failures, pairs, time per pair,
the truth's ATE, RPE and lane disagreement) it follows in its own columns or table.
Numbers are metres or the paper's unitless image metrics; "—" where a value does not
apply or could not be measured (a quadrat never located, a method that never answered).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tools.evaluation import paper
from tools.evaluation.blending import BLENDING_NAMES
from tools.evaluation.registration import BASELINE_NAMES

METRIC_KEYS = ("entropy", "variance", "rms_contrast", "tenengrad", "variance_of_laplacian")
MODE_NAMES = {
    "fmt-only": "FMT only",
    "gps-only": "Global prior only (gps-only)",
    "single-stage": "Ours (single-stage)",
    "two-stage": "Ours (two-stage)",
}


def _n(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if isinstance(value, int):
        return str(value)
    return f"{float(value):.{digits}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return [*lines, ""]


def _pair(ours: Any, theirs: Any) -> str:
    """Ours, with the paper's in brackets."""
    return f"{_n(ours)} ({_n(theirs)})"


def markdown(tables: dict[str, Any]) -> str:
    out = [
        f"# The paper's evaluation on {tables['survey']}",
        "",
        f"{tables['frames']} frames. Each cell: ours (the paper's, Zhang et al.). Inputs: "
        + ", ".join(f"{k} `{v}`" for k, v in tables["inputs"].items() if v),
        "",
        "## Table I: preprocessing",
        "",
    ]
    header = ["configuration", "Ent.", "Var.", "RMS", "Ten.", "VoL", "SS", "frames"]
    rows = []
    for name, row in tables["table_i"].items():
        theirs_i: Sequence[float | None] = paper.TABLE_I.get(name, (None,) * 6)
        values = [row[k] for k in METRIC_KEYS] + [row["similarity"]]
        rows.append([name, *(_pair(v, t) for v, t in zip(values, theirs_i, strict=True)),
                     _n(int(row["frames"]))])  # fmt: skip
    out += _table(header, rows)

    t2 = tables["table_ii"]
    out += ["## Table II: relative-pose consistency (m)", "",
            f"Over {t2['pairs']} consecutive pairs; baselines register each pair from identity "
            "with no prior; a failed pair is left out and counted.", ""]  # fmt: skip
    header = ["method", "vs FMT-only MAE", "RMSE", "vs gps-only MAE", "RMSE", "pairs", "failed"]
    rows = []
    for method, row in t2["rows"].items():
        theirs_ii: Sequence[float | None] = paper.TABLE_II.get(method, (None,) * 4)
        fmt, gps = row.get("vs_fmt-only", {}), row.get("vs_gps-only", {})
        name = BASELINE_NAMES.get(method) or MODE_NAMES.get(method, method)
        rows.append([
            name,
            _pair(fmt.get("mae_m"), theirs_ii[0]), _pair(fmt.get("rmse_m"), theirs_ii[1]),
            _pair(gps.get("mae_m"), theirs_ii[2]), _pair(gps.get("rmse_m"), theirs_ii[3]),
            _n(max(fmt.get("pairs", 0), gps.get("pairs", 0))), _n(row.get("failed")),
        ])  # fmt: skip
    out += _table(header, rows)
    out += ["Time per pair on this machine (preparing both frames included):", ""]
    out += _table(
        ["method", "ms per pair", "failed"],
        [
            [("FMT" if m == "fmt" else BASELINE_NAMES[m]), _n(r["ms_per_pair"], 1), _n(r["failed"])]
            for m, r in t2["pairwise"].items()
        ],
    )
    reference = t2.get("reference", {})
    if "truth" in t2:
        against = (
            "the reference trajectory"
            if reference.get("kind") == "reference trajectory"
            else "the truth"
        )
        matched = (
            f" {reference['frames_matched']} of {reference['frames']} frames had a reference pose."
            if "frames_matched" in reference
            else ""
        )
        out += [f"Against {against} (baselines: their steps chained from the first gps-only "
                f"pose, a failed step bridged by gps-only's).{matched}", ""]  # fmt: skip
        out += _table(
            ["method", "ATE (m)", "ATE aligned (m)", "RPE 10 s (m)", "lanes RMS (m)",
             "lanes median (m)"],
            [[BASELINE_NAMES.get(m) or MODE_NAMES.get(m) or "FMT pairwise, chained",
              _n(r["ate_m"]), _n(r["ate_aligned_m"]), _n(r["rpe_10s_m"]), _n(r["lanes_rms_m"]),
              _n(r["lanes_median_m"])] for m, r in t2["truth"].items()],
        )  # fmt: skip

    out += ["## Table III: quadrat spacing (m)", ""]
    rows = []
    for mode, spacing in tables["table_iii"].items():
        theirs_iii: Sequence[float | None] = paper.TABLE_III.get(mode, (None, None))
        spacing = spacing or {}
        located = _n(spacing.get("located"), 0)
        rows.append([MODE_NAMES[mode], _pair(spacing.get("mae"), theirs_iii[0]),
                     _pair(spacing.get("rmse"), theirs_iii[1]), located])  # fmt: skip
    if all(v is None for v in tables["table_iii"].values()):
        out += ["No quadrats known (give `--truth` or `--quadrats`).", ""]
        if reference.get("unavailable"):
            out += [f"The reference trajectory: {reference['unavailable']}.", ""]
    else:
        out += _table(["method", "MAE", "RMSE", "located"], rows)

    t4 = tables["table_iv"]
    out += [f"## Table IV: lambda (alpha = 1/{1 / t4['alpha']:.0f})", ""]
    rows = []
    for lam, row in t4["rows"].items():
        theirs_iv: Sequence[float | None] = paper.TABLE_IV.get(float(lam), (None, None))
        spacing = row.get("spacing") or {}
        rows.append([
            lam, _pair(spacing.get("mae"), theirs_iv[0]), _pair(spacing.get("rmse"), theirs_iv[1]),
            _n(row["vs_fmt-only"]["rmse_m"]), _n(row["vs_gps-only"]["rmse_m"]),
            _n(row.get("ate_aligned_m")),
        ])  # fmt: skip
    out += _table(["lambda", "spacing MAE", "spacing RMSE", "RMSE vs FMT-only",
                   "RMSE vs gps-only", "ATE aligned"], rows)  # fmt: skip

    out += ["## Table V: blending", ""]
    rows = []
    for method, row in tables["table_v"].items():
        theirs_v: Sequence[float | None] = paper.TABLE_V.get(method, (None,) * 5)
        rows.append([BLENDING_NAMES[method],
                     *(_pair(row[k], t) for k, t in zip(METRIC_KEYS, theirs_v, strict=True)),
                     _n(row["seconds"], 1)])  # fmt: skip
    out += _table(["method", "Ent.", "Var.", "RMS", "Ten.", "VoL", "render (s)"], rows)

    out += ["## Figures", ""]
    out += [f"![{name}]({name})" for name in tables.get("figures", [])]
    return "\n".join(out) + "\n"


def write_report(path: Path, tables: dict[str, Any]) -> None:
    path.write_text(markdown(tables), encoding="utf-8")
