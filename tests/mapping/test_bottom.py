"""The seabed under each ping: a ping over a slope lands where the world puts it, and the
echosounder's soundings give the altitude and the slope ping by ping.

The world here is the simulator's own sonar model (``tools.sim.sonar``: where each bin's
cone meets the sloping seabed plane, written in world north/east/down with its own
rotations), never the mapper's geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.bottom import (
    BottomModel,
    BottomParams,
    EchosounderMount,
    SeabedAttitude,
    pose_interpolator,
    sounding_points,
)
from mapping.polar import Attitude, FanGeometry, head_pose, polar_to_seabed
from mapping.samples import RangeSample
from tools.sim import sonar as world
from tools.sim.scenarios import resolve_scenario
from tools.sim.seabed import Seabed


def _world_seabed(depth0: float, slope_north: float, slope_east: float) -> Seabed:
    """A flat (relief-free) seabed plane in the simulator's own terms."""
    n = 8
    zeros = np.zeros((n, n), np.float32)
    return Seabed(
        west=-50.0,
        north=50.0,
        resolution=100.0 / n,
        reflectivity=np.full((n, n), 80, np.uint8),
        height=zeros,
        depth0=depth0,
        slope_north=slope_north,
        slope_east=slope_east,
    )


@pytest.mark.parametrize(
    ("heading_deg", "slope_north", "slope_east", "roll_deg", "pitch_deg"),
    [(0.0, 0.08, 0.0, 0.0, 0.0), (35.0, -0.06, 0.07, 2.5, -2.0), (200.0, 0.0, -0.1, -3.0, 2.0)],
)
def test_a_ping_over_a_slope_lands_where_the_world_puts_it(
    heading_deg: float, slope_north: float, slope_east: float, roll_deg: float, pitch_deg: float
) -> None:
    s = resolve_scenario("quadrats", n_beams=64, randomise=False)
    model = world.SonarModel.from_scenario(s, np.random.default_rng(0))
    heading, roll, pitch = (math.radians(v) for v in (heading_deg, roll_deg, pitch_deg))
    # Body -> world (NED): yaw, pitch, roll (ZYX), the antenna at the origin, 0.1 m up.
    cy, sy = math.cos(heading), math.sin(heading)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    body = rz @ ry @ rx
    antenna = np.array([0.0, 0.0, -0.1])
    seabed = _world_seabed(1.5, slope_north, slope_east)
    pose = world.sonar_pose(antenna, body, model)
    fp = world.footprint(model, pose, seabed, angles=False)

    # The mapper: the level sonar position's height above the bed straight below it, the
    # slope in the heading frame; C's origin is that level position.
    mount = (s.mount_x_m, s.mount_y_m, s.mount_z_m)
    level_sonar = antenna + rz @ np.array(mount)
    depth_below = 1.5 + slope_north * level_sonar[0] + slope_east * level_sonar[1]
    altitude = depth_below - level_sonar[2]
    slope_forward = slope_north * cy + slope_east * sy
    slope_starboard = -slope_north * sy + slope_east * cy
    fan = FanGeometry.of(
        model.bearings_rad,
        model.n_ranges,
        model.range_resolution_m,
        1.0,
        math.radians(s.tilt_deg),
        lever_arm_m=mount,
    )
    head = head_pose(fan, Attitude(roll, pitch, altitude, slope_forward, slope_starboard))
    slant = model.ranges_m[:, None] * np.ones(model.n_beams)[None, :]
    bearing = np.ones(model.n_ranges)[:, None] * model.bearings_rad[None, :]
    forward, starboard = polar_to_seabed(slant, bearing, head)
    north = level_sonar[0] + forward * cy - starboard * sy
    east = level_sonar[1] + forward * sy + starboard * cy
    both = fp.valid & np.isfinite(forward)
    assert both.sum() > 0.5 * fp.valid.sum()
    error = np.hypot(north - fp.north, east - fp.east)[both]
    assert float(np.max(error)) < 0.005  # float32 world against float64 mapper

    # The same ping taken as level at that altitude lands decimetres off at the far end.
    flat = head_pose(fan, Attitude(roll, pitch, altitude))
    f2, s2 = polar_to_seabed(slant, bearing, flat)
    n2 = level_sonar[0] + f2 * cy - s2 * sy
    e2 = level_sonar[1] + f2 * sy + s2 * cy
    ok = both & np.isfinite(f2)
    assert float(np.percentile(np.hypot(n2 - fp.north, e2 - fp.east)[ok], 90)) > 0.05


def _lawnmower_soundings(
    slope_east: float, slope_north: float, tide_mps: float, seed: int
) -> tuple[list[RangeSample], np.ndarray, np.ndarray, EchosounderMount]:
    """Soundings of a boat on three 16 m lanes 4 m apart at 0.5 m/s over a sloping bed
    (depth 1.6 m below the antenna at the origin), through a tide, with noise, dropouts
    and a few false short returns; and the boat's poses at 5 Hz."""
    rng = np.random.default_rng(seed)
    mount = EchosounderMount(forward_m=0.2, starboard_m=-0.1, down_m=0.25)
    times, poses = [], []
    t = 0.0
    for lane, east in enumerate((-4.0, 0.0, 4.0)):
        heading = 0.0 if lane % 2 == 0 else math.pi
        for north in np.arange(-8.0, 8.0, 0.1):
            poses.append((east, north if lane % 2 == 0 else -north, heading))
            times.append(t)
            t += 0.2
        t += 20.0  # the turn
    times_a, poses_a = np.array(times), np.array(poses)
    soundings = []
    norm = math.sqrt(1 + slope_east**2 + slope_north**2)
    for k in range(0, len(times_a), 1):
        e0, n0, psi = poses_a[k]
        e = e0 + mount.forward_m * math.sin(psi) + mount.starboard_m * math.cos(psi)
        n = n0 + mount.forward_m * math.cos(psi) - mount.starboard_m * math.sin(psi)
        depth = 1.6 + slope_east * e + slope_north * n - tide_mps * times_a[k]
        distance = (depth - mount.down_m) / norm + rng.normal(0.0, 0.01)
        if rng.random() < 0.03:
            continue  # a dropout
        if rng.random() < 0.01:
            distance *= 0.4  # weed, a fish
        soundings.append(RangeSample(float(times_a[k]), distance, 0.3, 30.0, 90, None, "test"))
    return soundings, times_a, poses_a, mount


@pytest.mark.parametrize(
    ("slope_east", "slope_north", "tide_mps"),
    [(0.0, 0.0, 0.0), (0.06, 0.0, 0.0), (0.04, -0.05, 8e-5), (-0.1, 0.02, -8e-5)],
)
def test_the_soundings_give_each_pings_altitude_and_slope(
    slope_east: float, slope_north: float, tide_mps: float
) -> None:
    soundings, times, poses, mount = _lawnmower_soundings(slope_east, slope_north, tide_mps, 3)
    vehicle_at = pose_interpolator(times, poses)
    points, stamps = sounding_points(soundings, vehicle_at, lambda _t: None, mount)
    assert len(points) == len(soundings)  # every reading within the span is placed
    sonar_down, lever = 0.3, (-0.45, 0.0)

    def sonar_pose(vehicle: np.ndarray) -> np.ndarray:
        psi = float(vehicle[2])
        return np.array(
            [
                vehicle[0] + lever[0] * math.sin(psi),
                vehicle[1] + lever[0] * math.cos(psi),
                psi,
            ]
        )

    model = BottomModel(points, stamps, sonar_down, (2.3, 4.9, 4.4), BottomParams())
    seabed = SeabedAttitude(model, vehicle_at, sonar_pose, None)
    errors, slopes = [], []
    for k in range(0, len(times), 7):
        attitude = seabed(float(times[k]))
        assert attitude is not None and attitude.altitude_m is not None
        e, n, psi = sonar_pose(poses[k])
        true_altitude = 1.6 + slope_east * e + slope_north * n - tide_mps * times[k] - sonar_down
        errors.append(attitude.altitude_m - true_altitude)
        forward = slope_east * math.sin(psi) + slope_north * math.cos(psi)
        starboard = slope_east * math.cos(psi) - slope_north * math.sin(psi)
        slopes.append((attitude.slope_forward - forward, attitude.slope_starboard - starboard))
    errors_a, slopes_a = np.abs(errors), np.abs(slopes)
    # Centimetres of altitude (soundings 1 cm, the false returns kept out), the slope to a
    # fraction of a percent along the lanes and across them (three lanes 4 m apart).
    assert float(np.median(errors_a)) < 0.01 and float(errors_a.max()) < 0.05
    assert float(np.median(slopes_a)) < 0.005 and float(slopes_a.max()) < 0.03


def test_without_soundings_near_a_ping_the_configured_altitude_stays() -> None:
    soundings, times, poses, mount = _lawnmower_soundings(0.05, 0.0, 0.0, 1)
    vehicle_at = pose_interpolator(times, poses)
    points, stamps = sounding_points(soundings, vehicle_at, lambda _t: None, mount)
    model = BottomModel(points, stamps, 0.3, (2.3, 4.9, 4.4), BottomParams())
    # 40 m away from every sounding: no plane.
    assert model.at(float(times[10]), np.array([40.0, 40.0, 0.0])) is None
    # Readings outside the sensor's span are not placed.
    odd = [RangeSample(1.0, 0.1), RangeSample(2.0, math.nan), RangeSample(3.0, 1.2)]
    pts, _ = sounding_points(odd, vehicle_at, lambda _t: None, mount)
    assert len(pts) == 1
