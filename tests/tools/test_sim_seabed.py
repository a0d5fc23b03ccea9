"""The seabed: bending ripple trains, smooth mud, racks of bars 1 m apart, oyster rows,
and the farm's three quadrat arrays."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from tools.sim import resolve_scenario
from tools.sim.features import features_section
from tools.sim.scenarios import Scenario
from tools.sim.seabed import Seabed, generate_seabed
from tools.sim.site import SiteFrame

FARM_BOUNDS = (-20.0, -17.0, 22.0, 15.0)


@pytest.fixture(scope="module")
def farm() -> tuple[Scenario, Seabed, dict[str, Any]]:
    """The farm's seabed at 2 cm (quick), over its arrays, racks and planted bed."""
    s = resolve_scenario("farm", seabed_resolution_m=0.02)
    bed = generate_seabed(s, FARM_BOUNDS, np.random.default_rng(3))
    site = SiteFrame.at(s.origin_lat_deg, s.origin_lon_deg)
    features = features_section(bed, site, s)
    local = (site.utm_east0, site.utm_north0)
    return s, bed, {"features": features, "origin": local}


def cells(bed: Seabed, east: np.ndarray, north: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    col, row = bed.pixel(east, north)
    return np.rint(row).astype(int), np.rint(col).astype(int)


def test_the_farm_has_three_quadrat_arrays(farm):
    _, _, data = farm
    features = data["features"]
    quadrats = features["quadrats"]
    assert len(quadrats) == 24 and len(features["quadrat_arrays"]) == 3
    keys = {"row", "index", "material", "side_m", "bar_width_m", "bar_height_m", "corners",
            "centre_east", "centre_north", "centre_local_east", "centre_local_north",
            "oysters"}  # fmt: skip
    for number in range(3):
        frames = [q for q in quadrats if q["array"] == number]
        assert len(frames) == 8
        assert all(keys <= set(q) for q in frames)
        for row, material in ((0, "aluminium"), (1, "pvc")):
            line = sorted((q for q in frames if q["row"] == row), key=lambda q: q["index"])
            assert [q["material"] for q in line] == [material] * 4
            centres = np.array([[q["centre_east"], q["centre_north"]] for q in line])
            spacing = np.linalg.norm(np.diff(centres, axis=0), axis=1)
            np.testing.assert_allclose(spacing, 1.0, atol=1e-5)
        centre = np.mean([[q["centre_east"], q["centre_north"]] for q in frames], axis=0)
        listed = features["quadrat_arrays"][number]
        np.testing.assert_allclose(centre, [listed["centre_east"], listed["centre_north"]])


def test_racks_are_rows_of_bars_a_metre_apart_standing_on_the_crests(farm):
    s, bed, data = farm
    e0, n0 = data["origin"]
    racks = data["features"]["racks"]
    assert len(racks) == len(s.racks) == 2
    for rack in racks:
        bars = np.array(rack["bars"])
        rows = bars[: rack["n_rows"]]
        starts = rows[:, :2]
        gaps = np.linalg.norm(np.diff(starts, axis=0), axis=1)
        np.testing.assert_allclose(gaps, 1.0, atol=1e-3)
        # Along the bars the bed stands a bar's height above the ripples' crests, bright.
        f = np.linspace(0.05, 0.95, 40)[:, None]
        pts = (rows[:, None, :2] + f * (rows[:, None, 2:] - rows[:, None, :2])).reshape(-1, 2)
        r, c = cells(bed, pts[:, 0] - e0, pts[:, 1] - n0)
        on_bars = np.median(bed.height[r, c])
        assert on_bars > 0.03
        assert np.median(bed.reflectivity[r, c]) > 2 * np.median(bed.reflectivity)
        # ...and between the rows it is sand.
        mid = (rows[:-1, :2] + rows[1:, :2]) / 2 + 0.5 * (rows[:-1, 2:] - rows[:-1, :2])
        r, c = cells(bed, mid[:, 0] - e0, mid[:, 1] - n0)
        assert np.all(bed.height[r, c] < on_bars - 0.02)


def test_an_oyster_bed_planted_in_rows(farm):
    s, bed, _ = farm
    planted = next(b for b in s.oyster_beds if b.row_spacing_m > 0)
    beta = math.radians(planted.bearing_deg)
    o = bed.oysters
    a = (o.east - planted.centre_east_m) * math.sin(beta) + (
        o.north - planted.centre_north_m
    ) * math.cos(beta)
    b = (o.east - planted.centre_east_m) * math.cos(beta) - (
        o.north - planted.centre_north_m
    ) * math.sin(beta)
    inside = (np.abs(a) < planted.length_m / 2) & (np.abs(b) < planted.width_m / 2)
    assert inside.sum() > 200
    # Across the bed the oysters bunch at the rows' spacing (and along them at the clumps').
    for coord, spacing in ((b, planted.row_spacing_m), (a, planted.clump_spacing_m)):
        phase = np.exp(2j * math.pi * coord[inside] / spacing)
        assert abs(np.mean(phase)) > 0.6


def test_mud_patches_are_smooth_and_featureless(farm):
    s, bed, data = farm
    e0, n0 = data["origin"]
    patches = data["features"]["mud_patches"]
    assert len(patches) == s.n_mud_patches
    res = bed.resolution
    n_idx = np.arange(bed.shape[0])
    e_idx = np.arange(bed.shape[1])
    east = bed.west + (e_idx + 0.5) * res
    north = bed.north - (n_idx + 0.5) * res
    distance = np.full(bed.shape, np.inf)
    for p in patches:
        d = np.hypot(east[None, :] - (p["east"] - e0), north[:, None] - (p["north"] - n0))
        distance = np.minimum(distance, d / p["radius_m"])
    bare = np.abs(bed.height) < 0.015  # off the oysters, frames and racks
    mud = (distance < 0.4) & bare
    sand = (distance > 2.0) & bare
    if mud.sum() < 1000:
        pytest.skip("the patches fell off this map")
    # (Robust spreads: a scattered clump or shell patch may lie on the mud.)
    mud_relief, sand_relief = (
        np.subtract(*np.percentile(bed.height[m], [75, 25])) for m in (mud, sand)
    )
    assert mud_relief < 0.25 * sand_relief
    # Texture: cell-to-cell contrast of the reflectivity.
    grad = np.abs(np.diff(bed.reflectivity.astype(float), axis=1))[:, :-1]
    assert np.median(grad[mud[:, :-2]]) < 0.4 * np.median(grad[sand[:, :-2]])
    assert np.median(bed.reflectivity[mud]) < np.median(bed.reflectivity[sand])


def _bare(**overrides: Any) -> Scenario:
    """Rippled sand and nothing else (the quadrats far off the map)."""
    s = resolve_scenario("quadrats", randomise=False, **overrides)
    return dataclasses.replace(
        s, n_shell_patches=0, n_mud_patches=0, scattered_clumps_per_m2=0.0,
        quadrat_centre_east_m=1000.0, quadrat_centre_north_m=1000.0,
    )  # fmt: skip


def test_ripple_crests_bend_and_their_wavelength_varies_across_the_site():
    """The documented local wave vector (``RippleTrain.local_wave``) turns by about
    ripple_bend_deg RMS over the site, and the painted relief follows it: its local
    spectral peak in windows across the site has the predicted wavelength and bearing."""
    s = _bare(ripple_bend_deg=15.0, ripple2_amplitude_m=0.0)
    bed = generate_seabed(s, (-20.0, -20.0, 20.0, 20.0), np.random.default_rng(8))
    train = bed.ripples[0]
    grid = np.linspace(-18.0, 18.0, 40)
    e, n = np.meshgrid(grid, grid)
    wavelength, bearing = train.local_wave(e, n)
    turn = np.degrees(np.angle(np.exp(1j * (bearing - train.bearing_rad))))
    assert np.std(turn) == pytest.approx(15.0, rel=0.5)
    assert 0.02 < np.std(wavelength) / np.mean(wavelength) < 0.3
    assert np.mean(wavelength) == pytest.approx(s.ripple_wavelength_m, rel=0.1)

    half = 128  # 2.56 m windows
    window = np.outer(np.hanning(2 * half), np.hanning(2 * half))
    k = np.fft.fftfreq(2 * half, bed.resolution)
    ke, kn = np.meshgrid(k, -k)  # rows run south
    bearings_seen = []
    for ce, cn in ((-12.0, -12.0), (12.0, 12.0), (-12.0, 12.0), (12.0, -12.0), (0.0, 0.0)):
        r, c = cells(bed, np.array(ce), np.array(cn))
        patch = bed.height[r - half : r + half, c - half : c + half].astype(float)
        power = np.abs(np.fft.fft2((patch - patch.mean()) * window)) ** 2
        power[np.hypot(ke, kn) < 1.5] = 0.0  # below 0.67 cycles/m: not these ripples
        peak = np.unravel_index(np.argmax(power), power.shape)
        seen_wavelength = 1.0 / math.hypot(ke[peak], kn[peak])
        seen_bearing = math.atan2(ke[peak], kn[peak])
        want_wavelength, want_bearing = train.local_wave(np.array(ce), np.array(cn))
        assert seen_wavelength == pytest.approx(float(want_wavelength), rel=0.12)
        diff = math.degrees(2 * (seen_bearing - float(want_bearing))) / 2  # modulo 180
        assert abs((diff + 90.0) % 180.0 - 90.0) < 12.0
        bearings_seen.append(seen_bearing)
    assert np.ptp(np.degrees(np.unwrap(2 * np.array(bearings_seen)) / 2)) > 5.0


def test_two_ripple_trains_are_superposed():
    s = _bare(ripple_amplitude_m=0.006, ripple2_amplitude_m=0.004, ripple_bend_deg=6.0)
    bed = generate_seabed(s, (-5.0, -5.0, 5.0, 5.0), np.random.default_rng(2))
    assert len(bed.ripples) == 2
    spectrum = np.abs(np.fft.rfft2(bed.height - bed.height.mean())) ** 2
    ky = np.fft.fftfreq(bed.shape[0], bed.resolution)[:, None]
    kx = np.fft.rfftfreq(bed.shape[1], bed.resolution)[None, :]
    radius = np.hypot(kx, ky)
    for wavelength in (s.ripple_wavelength_m, s.ripple2_wavelength_m):
        band = np.abs(radius - 1.0 / wavelength) < 0.15 / wavelength
        assert spectrum[band].sum() > 0.2 * spectrum.sum() * band.mean() / 0.05
