"""Ablations of the paper's Tables I and IV on a recorded (or simulated) survey.

    python -m tools.ablation preprocess SURVEY_DIR [--every N]
    python -m tools.ablation lambda SURVEY_DIR

``SURVEY_DIR`` holds ``sonar.oculus``, ``nav.tlog``, ``site.toml`` (and ``truth.json`` for
the lambda table). ``preprocess`` reports, per preprocessing configuration, the image
metrics of the Cartesian frames (entropy, variance, RMS contrast, Tenengrad, variance of
Laplacian) and the similarity score of consecutive registrations (the mean NCC peak);
``lambda`` replays single-stage with lambda from 1e2 to 1e6 and reports the quadrat
spacing error against the truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drivers.oculus.logfile import iter_pings
from mapping.fmt import FmtRegistrar
from mapping.frames import LocalRegistration
from mapping.metrics import image_metrics
from mapping.preprocess import PreprocessParams
from seamap.config import load_config

CONFIGURATIONS: dict[str, PreprocessParams] = {
    "raw": PreprocessParams(equalize_rows=False, histogram_match=False, clahe=False),
    "eq": PreprocessParams(histogram_match=False, clahe=False),
    "eq+median": PreprocessParams(histogram_match=False, clahe=False, denoise="median"),
    "eq+nlm": PreprocessParams(histogram_match=False, clahe=False, denoise="nlm"),
    "clahe": PreprocessParams(equalize_rows=False),
    "eq+clahe (default)": PreprocessParams(),
    "eq+median+clahe": PreprocessParams(denoise="median"),
    "eq+nlm+clahe": PreprocessParams(denoise="nlm"),
    "eq+clahe+blur": PreprocessParams(blur=True),
}


def preprocessing_table(survey: Path, every: int = 10) -> dict[str, dict[str, float]]:
    """Mean metrics per configuration over every ``every``-th frame (and its successor,
    for the similarity score)."""
    from seamap.replay import mount_from_config

    config = load_config(survey / "site.toml")
    mount = mount_from_config(config.sonar)
    table: dict[str, dict[str, float]] = {}
    for name, params in CONFIGURATIONS.items():
        local = LocalRegistration(mount, params)
        rows: list[dict[str, float]] = []
        scores: list[float] = []
        previous = None
        for index, ping in enumerate(iter_pings(survey / "sonar.oculus")):
            if index % every not in (0, 1):
                continue
            frame = local.frame(ping)
            registrar = local.registrar
            assert isinstance(registrar, FmtRegistrar)
            if index % every == 0:
                rows.append(image_metrics(frame.image.astype(float), frame.mask))
                previous = registrar.prepare(frame.coarse)
            elif previous is not None:
                scores.append(registrar.register(previous, registrar.prepare(frame.coarse)).score)
        means = {key: float(np.mean([r[key] for r in rows])) for key in rows[0]}
        means["similarity"] = float(np.mean(scores)) if scores else float("nan")
        table[name] = means
    return table


def lambda_table(
    survey: Path, lambdas: Sequence[float] = (1e2, 1e3, 1e4, 1e5, 1e6)
) -> dict[float, dict[str, float]]:
    from seamap.replay import pipeline_params, replay

    config = load_config(survey / "site.toml")
    base = pipeline_params(config)
    out: dict[float, dict[str, float]] = {}
    for lam in lambdas:
        # Single-stage weighs registrations by their covariance; lambda / 1e4 scales it.
        graph = dataclasses.replace(base.single_stage.graph, registration_scale=lam / 1e4)
        params = dataclasses.replace(
            base, single_stage=dataclasses.replace(base.single_stage, graph=graph)
        )
        report = replay(
            survey / "sonar.oculus", survey / "nav.tlog", survey / "site.toml", "single-stage",
            survey / f"lambda-{lam:g}", truth=survey / "truth.json", params=params,
        )  # fmt: skip
        accuracy = report["accuracy"]
        out[lam] = {
            "quadrat_mae": accuracy["quadrat_spacing"]["mae"],
            "quadrat_rmse": accuracy["quadrat_spacing"]["rmse"],
            "aligned_ate": accuracy["trajectory"]["aligned_rmse"],
            "distortion": accuracy["mosaic_vs_seabed"]["distortion_rms_m"],
        }
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.ablation", description=__doc__)
    parser.add_argument("table", choices=("preprocess", "lambda"))
    parser.add_argument("survey", type=Path)
    parser.add_argument("--every", type=int, default=10)
    args = parser.parse_args(argv)
    if args.table == "preprocess":
        table = preprocessing_table(args.survey, args.every)
        keys = [
            "entropy",
            "variance",
            "rms_contrast",
            "tenengrad",
            "variance_of_laplacian",
            "similarity",
        ]
        print(f"{'configuration':22s} " + " ".join(f"{k[:8]:>8s}" for k in keys))
        for name, row in table.items():
            print(f"{name:22s} " + " ".join(f"{row[k]:8.4f}" for k in keys))
    else:
        for lam, row in lambda_table(args.survey).items():
            print(f"lambda {lam:8.0e}  " + "  ".join(f"{k} {v:.4f}" for k, v in row.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
