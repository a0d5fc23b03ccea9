"""The seed paper's published numbers (Zhang et al., Tables I-V), to print ours beside.

Field data: an oyster farm's 2 x 4 quadrat site, 180-400+ frames a sequence, Table I
averaged over 15 trials. Image metrics are on intensities in [0, 1].
"""

from __future__ import annotations

TABLE_I: dict[str, tuple[float, ...]] = {
    # configuration: (Ent., Var., RMS, Ten., VoL, SS)
    "raw": (0.905, 0.036, 0.189, 0.333, 0.687, 0.184),
    "eq": (0.921, 0.035, 0.187, 0.358, 0.743, 0.178),
    "eq+median": (0.864, 0.035, 0.188, 0.099, 0.060, 0.143),
    "eq+nlm": (0.892, 0.035, 0.188, 0.268, 0.538, 0.180),
    "clahe": (0.966, 0.056, 0.237, 0.742, 1.550, 0.174),
    "eq+clahe (default)": (0.963, 0.052, 0.228, 0.804, 1.701, 0.166),
    "eq+median+clahe": (0.953, 0.048, 0.218, 0.180, 0.108, 0.140),
    "eq+nlm+clahe": (0.955, 0.055, 0.234, 0.631, 1.281, 0.172),
    "eq+clahe+blur": (0.941, 0.044, 0.210, 0.308, 0.154, 0.178),
}

TABLE_II: dict[str, tuple[float | None, ...]] = {
    # method: (MAE vs FMT-only, RMSE vs FMT-only, MAE vs gps-only, RMSE vs gps-only), m
    "orb": (0.316, 1.173, 0.304, 1.161),
    "sift": (1.058, 2.807, 1.048, 2.800),
    "ecc": (0.069, 0.106, 0.066, 0.085),
    "fmt-only": (None, None, 0.042, 0.064),
    "gps-only": (0.042, 0.064, None, None),
    "single-stage": (0.005, 0.006, 0.038, 0.062),
}

TABLE_III: dict[str, tuple[float, ...]] = {
    # mode: (MAE, RMSE) of the quadrat spacing, m
    "fmt-only": (0.189, 0.221),
    "single-stage": (0.173, 0.200),
    "two-stage": (0.176, 0.207),
}

TABLE_IV: dict[float, tuple[float, ...]] = {
    # lambda: (MAE, RMSE) of the quadrat spacing, m (alpha = 1/225)
    1e2: (0.476, 0.606),
    1e3: (0.429, 0.503),
    1e4: (0.173, 0.200),
    1e5: (0.201, 0.248),
    1e6: (0.225, 0.262),
}

TABLE_V: dict[str, tuple[float, ...]] = {
    # blending: (Ent., Var., RMS, Ten., VoL)
    "average": (0.619, 0.036, 0.189, 0.042, 0.039),
    "hurtos": (0.634, 0.035, 0.186, 0.047, 0.047),
    "su": (0.656, 0.043, 0.208, 0.084, 0.077),
    "robust": (0.680, 0.048, 0.219, 0.142, 0.145),
}
