"""truth.json's ``features``: the quadrat arrays, racks, oysters, patches and ripples.

UTM metres of the site's zone (local + the UTM origin); bearings in degrees clockwise
from grid north. See ``truth.py`` for the whole schema.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from tools.sim.jsonround import round_json
from tools.sim.scenarios import Scenario
from tools.sim.seabed import (
    ALUMINIUM_SIDE_M,
    FRAME_SPACING_M,
    PVC_SIDE_M,
    ROW_CENTRE_DISTANCE_M,
    ROW_GAP_M,
    Seabed,
)
from tools.sim.site import SiteFrame
from tools.sim.structures import rack_bars


def _patches(patches: Any, e0: float, n0: float) -> list[dict[str, float]]:
    return [
        {
            "east": round_json(p.centre_east + e0, 3),
            "north": round_json(p.centre_north + n0, 3),
            "radius_m": round_json(p.radius_m, 3),
        }
        for p in patches
    ]


def _ripples(seabed: Seabed, s: Scenario) -> dict[str, Any]:
    trains = [
        {
            "wavelength_m": round_json(t.wavelength_m),
            "amplitude_m": round_json(t.amplitude_m),
            "bearing_deg": round_json(math.degrees(t.bearing_rad) % 360.0),
            "bend_deg": round_json(math.degrees(t.bend_rad)),
            "warp": {
                "k_east_rad_per_m": round_json(t.warp_k_east),
                "k_north_rad_per_m": round_json(t.warp_k_north),
                "amplitude_m": round_json(t.warp_amplitude_m),
                "phase_rad": round_json(t.warp_phase),
            },
        }
        for t in seabed.ripples
    ]
    return {
        "wavelength_m": s.ripple_wavelength_m,
        "amplitude_m": s.ripple_amplitude_m,
        "bearing_deg": s.ripple_bearing_deg,
        "profile": "amplitude * envelope * (sin phi - 0.2 cos 2 phi), phi = 2 pi / "
        "wavelength_m (u . x + warp(x)) + defects; warp(x) = sum_j amplitude_m_j "
        "sin(k_j . x + phase_j), x local east/north metres; u the unit vector of "
        "bearing_deg; envelope and defects random fields (not given)",
        "trains": trains,
    }


def features_section(seabed: Seabed, site: SiteFrame, s: Scenario) -> dict[str, Any]:
    """The truth's ``features``: quadrat arrays, racks, oysters, shell and mud patches,
    ripples, the seabed type, gravel patches and debris (``bottoms``; UTM)."""
    e0, n0 = site.utm_east0, site.utm_north0
    oysters = seabed.oysters
    in_quadrat = np.bincount(oysters.quadrat[oysters.quadrat >= 0], minlength=len(seabed.quadrats))
    quadrats = []
    for qi, q in enumerate(seabed.quadrats):
        corners = q.corners() + np.array([e0, n0])
        quadrats.append(
            {
                "row": q.row,
                "index": q.index,
                "material": q.material,
                "side_m": q.side_m,
                "bar_width_m": q.bar_width_m,
                "bar_height_m": q.bar_height_m,
                "centre_east": round_json(q.centre_east + e0),
                "centre_north": round_json(q.centre_north + n0),
                "centre_local_east": round_json(q.centre_east),
                "centre_local_north": round_json(q.centre_north),
                "corners": round_json(corners),
                "oysters": int(in_quadrat[qi]),
                "array": q.array,
            }
        )
    arrays = [
        (s.quadrat_centre_east_m, s.quadrat_centre_north_m, s.quadrat_row_bearing_deg),
        *((a.centre_east_m, a.centre_north_m, a.row_bearing_deg) for a in s.quadrat_arrays),
    ]
    racks = []
    for rack in s.racks:
        bars = rack_bars(rack) + np.array([e0, n0, e0, n0])
        racks.append(
            {
                "centre_east": round_json(rack.centre_east_m + e0),
                "centre_north": round_json(rack.centre_north_m + n0),
                "bearing_deg": rack.bearing_deg,
                "length_m": rack.length_m,
                "n_rows": rack.n_rows,
                "row_spacing_m": rack.row_spacing_m,
                "tie_spacing_m": rack.tie_spacing_m,
                "bar_width_m": rack.bar_width_m,
                "bar_height_m": rack.bar_height_m,
                "bars": round_json(bars, 4),
            }
        )
    return {
        "quadrat_layout": {
            "aluminium_side_m": ALUMINIUM_SIDE_M,
            "pvc_side_m": PVC_SIDE_M,
            "row_gap_m": ROW_GAP_M,
            "frame_spacing_m": FRAME_SPACING_M,
            "row_centre_distance_m": round_json(ROW_CENTRE_DISTANCE_M),
            "row_bearing_deg": s.quadrat_row_bearing_deg,
            "centre_east": round_json(s.quadrat_centre_east_m + e0),
            "centre_north": round_json(s.quadrat_centre_north_m + n0),
            "sides": "side_m is measured between bar centre lines; row_gap_m between the "
            "centre lines of the rows' nearest sides; this block describes array 0",
        },
        "quadrat_arrays": [
            {
                "array": number,
                "centre_east": round_json(east + e0),
                "centre_north": round_json(north + n0),
                "row_bearing_deg": bearing,
            }
            for number, (east, north, bearing) in enumerate(arrays)
        ],
        "quadrats": quadrats,
        "racks": racks,
        "oysters": {
            "count": len(oysters),
            "east": round_json(oysters.east + e0, 3),
            "north": round_json(oysters.north + n0, 3),
            "length_m": round_json(oysters.length, 3),
            "width_m": round_json(oysters.width, 3),
            "height_m": round_json(oysters.height, 3),
            "bearing_deg": round_json(np.degrees(oysters.bearing) % 360.0, 1),
            "clump": oysters.clump.tolist(),
            "quadrat": oysters.quadrat.tolist(),
        },
        "shell_patches": _patches(seabed.shell_patches, e0, n0),
        "mud_patches": _patches(seabed.mud_patches, e0, n0),
        "ripples": _ripples(seabed, s),
        "seabed_type": seabed.seabed_type,
        "gravel_patches": _patches(seabed.gravel_patches, e0, n0),
        "debris": [
            {
                "kind": d.kind,
                "east": round_json(d.centre_east + e0, 3),
                "north": round_json(d.centre_north + n0, 3),
                "bearing_deg": round_json(d.bearing_deg, 2),
                "length_m": round_json(d.length_m, 3),
                "width_m": round_json(d.width_m, 3),
                "height_m": round_json(d.height_m, 3),
                "reflectivity": d.reflectivity,
            }
            for d in seabed.debris
        ],
    }
