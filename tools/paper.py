"""Reproduce the paper's tables on simulated quadrat surveys (``make paper``).

    python -m tools.paper --out paper-out [--seeds 1 2 3] [--jobs 2] [--max-pings N]

Each seed's quadrat survey (``seamap simulate --scenario quadrats``: the paper's 2 x 4
quadrat site on a simulated field day) is evaluated by ``seamap evaluate`` into
``OUT/report-sN/``; ``OUT/summary.md`` then gives every table with, per cell, the median
over the surveys and their range, beside the paper's published number. A number from one
survey is an anecdote: the range says how much a field day moves it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from tools.evaluation import paper
from tools.evaluation.blending import BLENDING_NAMES
from tools.evaluation.registration import BASELINE_NAMES
from tools.evaluation.report import METRIC_KEYS, MODE_NAMES


def evaluate_seed(out: Path, seed: int, max_pings: int | None) -> dict[str, Any]:
    """Simulate and evaluate one survey (in its own process); its tables."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from tools.evaluation.run import evaluate_survey, resolve_inputs
    from tools.sim import simulate

    sim = out / f"sim-s{seed}"
    if not (sim / "truth.json").is_file():
        simulate("quadrats", seed, sim, max_pings=max_pings)
    report = out / f"report-s{seed}"
    log = open(out / f"report-s{seed}.log", "w", encoding="utf-8")  # noqa: SIM115
    with log:
        inputs = resolve_inputs(sim, None, None, None, None, None)
        return evaluate_survey(inputs, report, say=lambda text: print(text, file=log, flush=True))


def _cell(values: Sequence[Any], theirs: Any = None, digits: int = 3) -> str:
    """Median [min, max] of the finite values, with the paper's number in brackets."""
    finite = [float(v) for v in values if isinstance(v, int | float) and math.isfinite(v)]
    if not finite:
        ours = "—"
    elif len(finite) == 1:
        ours = f"{finite[0]:.{digits}f}"
    else:
        ours = (
            f"{np.median(finite):.{digits}f} [{min(finite):.{digits}f}, {max(finite):.{digits}f}]"
        )
    if theirs is None:
        return ours
    return f"{ours} ({theirs:.{digits}f})"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *("| " + " | ".join(r) + " |" for r in rows), ""]  # fmt: skip


def summary(runs: list[dict[str, Any]], seeds: Sequence[int]) -> str:
    """Every table over the surveys: median [min, max] (the paper's)."""
    out = [
        f"# The paper's tables on {len(runs)} simulated quadrat surveys (seeds "
        f"{', '.join(map(str, seeds))})",
        "",
        "Each cell: the median over the surveys [their range] (the paper's number).",
        "",
        "## Table I: preprocessing",
        "",
    ]
    rows = []
    for name, theirs_i in paper.TABLE_I.items():
        cells = [
            _cell([r["table_i"][name][k] for r in runs], t)
            for k, t in zip([*METRIC_KEYS, "similarity"], theirs_i, strict=True)
        ]
        rows.append([name, *cells])
    out += _table(["configuration", "Ent.", "Var.", "RMS", "Ten.", "VoL", "SS"], rows)

    out += ["## Table II: relative-pose consistency (m)", ""]
    rows = []
    for method, theirs_ii in paper.TABLE_II.items():
        name = BASELINE_NAMES.get(method) or MODE_NAMES[method]
        cells = []
        for ref, (mae, rmse) in (("fmt-only", theirs_ii[:2]), ("gps-only", theirs_ii[2:])):
            got = [r["table_ii"]["rows"][method].get(f"vs_{ref}") for r in runs]
            cells += [
                _cell([g["mae_m"] if g else None for g in got], mae),
                _cell([g["rmse_m"] if g else None for g in got], rmse),
            ]
        failed = _cell([r["table_ii"]["rows"][method].get("failed") for r in runs], digits=0)
        rows.append([name, *cells, failed])
    two = [r["table_ii"]["rows"]["two-stage"] for r in runs]
    rows.append([MODE_NAMES["two-stage"],
                 _cell([g["vs_fmt-only"]["mae_m"] for g in two]),
                 _cell([g["vs_fmt-only"]["rmse_m"] for g in two]),
                 _cell([g["vs_gps-only"]["mae_m"] for g in two]),
                 _cell([g["vs_gps-only"]["rmse_m"] for g in two]), "—"])  # fmt: skip
    out += _table(["method", "vs FMT MAE", "RMSE", "vs gps-only MAE", "RMSE", "failed pairs"], rows)
    out += ["Time per pair (ms) and, against the truth, ATE after alignment and lane "
            "disagreement (m):", ""]  # fmt: skip
    rows = []
    for method in ("fmt", "orb", "sift", "ecc"):
        key = "fmt-pairwise" if method == "fmt" else method
        rows.append([
            "FMT" if method == "fmt" else BASELINE_NAMES[method],
            _cell([r["table_ii"]["pairwise"][method]["ms_per_pair"] for r in runs], digits=1),
            _cell([r["table_ii"]["truth"][key]["ate_aligned_m"] for r in runs]),
            _cell([r["table_ii"]["truth"][key]["lanes_rms_m"] for r in runs]),
        ])  # fmt: skip
    for mode in ("fmt-only", "gps-only", "single-stage", "two-stage"):
        rows.append([
            MODE_NAMES[mode], "—",
            _cell([r["table_ii"]["truth"][mode]["ate_aligned_m"] for r in runs]),
            _cell([r["table_ii"]["truth"][mode]["lanes_rms_m"] for r in runs]),
        ])  # fmt: skip
    out += _table(["method", "ms per pair", "ATE aligned", "lanes RMS"], rows)

    out += ["## Table III: quadrat spacing (m)", ""]
    rows = []
    for mode, (mae, rmse) in paper.TABLE_III.items():
        got = [r["table_iii"][mode] or {} for r in runs]
        rows.append([MODE_NAMES[mode], _cell([g.get("mae") for g in got], mae),
                     _cell([g.get("rmse") for g in got], rmse)])  # fmt: skip
    out += _table(["method", "MAE", "RMSE"], rows)

    out += ["## Table IV: lambda (alpha = 1/225), quadrat spacing (m)", ""]
    rows = []
    for lam, (mae, rmse) in paper.TABLE_IV.items():
        got = [(r["table_iv"]["rows"][f"{lam:.0e}"].get("spacing") or {}) for r in runs]
        rows.append([f"{lam:.0e}", _cell([g.get("mae") for g in got], mae),
                     _cell([g.get("rmse") for g in got], rmse)])  # fmt: skip
    out += _table(["lambda", "MAE", "RMSE"], rows)

    out += ["## Table V: blending", ""]
    rows = []
    for method, theirs_v in paper.TABLE_V.items():
        cells = [_cell([r["table_v"][method][k] for r in runs], t)
                 for k, t in zip(METRIC_KEYS, theirs_v, strict=True)]  # fmt: skip
        rows.append([BLENDING_NAMES[method], *cells])
    out += _table(["method", "Ent.", "Var.", "RMS", "Ten.", "VoL"], rows)
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.paper", description=__doc__)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--max-pings", type=int, default=None)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(max_workers=max(args.jobs, 1)) as pool:
        futures = [pool.submit(evaluate_seed, args.out, s, args.max_pings) for s in args.seeds]
        runs = [f.result() for f in futures]
    (args.out / "tables.json").write_text(json.dumps(runs, indent=1) + "\n")
    text = summary(runs, args.seeds)
    (args.out / "summary.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
