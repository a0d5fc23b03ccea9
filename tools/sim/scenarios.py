"""Survey scenarios: every number the simulator uses, in one frozen record per scenario.

A ``Scenario`` holds the site (where, seabed, features), the survey (lawnmower, boat
motion), the sonar (M1200d in low-frequency mode) and the sensor error models. Units are
SI with the unit in the name where it helps (``_m``, ``_s``, ``_mps``); angles at this
edge are degrees (``_deg``) and bearings are grid bearings (degrees clockwise from UTM
grid north) unless the name says ``true``. Positions ``*_east_m``/``*_north_m`` are in the
site's local frame: metres east/north of the site's UTM origin point (grid-aligned).

``SCENARIOS`` maps the public names (``quadrats``, ``farm``, ``quadrats-current``,
``hectare``, and the conditions users met: ``shore``, ``mud``, ``deep``, ``rtk``,
``field``) to their records; ``resolve_scenario`` applies keyword overrides (any
field, e.g. ``max_pings=20, n_beams=128, flavour="px4"``) and checks them.

Each seed is a new field day: with ``randomise`` (the default) ``prepare_survey`` draws the
sensor errors, latencies, waves and bedforms of the day within realistic ranges
(``tools.sim.fieldday``), except the fields the caller set explicitly (``explicit``, which
``resolve_scenario`` fills from the overrides). The values below are those defaults, used
as they are when ``randomise`` is false.

The conditions users reported, each on the quadrats' site and array: ``shore`` (the bed
deepening 6.25 % across five lanes, the sonar 1.1-2.1 m above it, a downward echosounder,
ArduPilot, an M8N), ``mud`` (a soft mud bottom), ``deep`` (3.5 m of water, 10 m range,
25 degrees tilt, 0.9 m/s, lanes spaced to the wider swath: ``swath``), ``rtk`` (an RTK
receiver at 5 Hz, the compass pinned 3 degrees off) and ``field`` (``wide``: all of it
drawn per seed, ``fieldday.draw_wide``); each runs 3-5 minutes.

``hectare`` is the 2-hour benchmark survey, meant for ``tools.sim.stream`` (``simulate``
needs a cut for it: ``STREAM_ONLY``). Its seabed cells are 2 cm instead of 1 cm: the
whole map is generated up front (about 1 s, 31 million cells, 155 MB kept, ~1.1 GB peak
while painting) rather than tiled on demand, which keeps one code path for every
scenario; the sonar's 1 cm range bins then see a slightly smoother bed.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any

from drivers.errors import SeamapError
from tools.sim.swath import lane_spacing_for, range_resolution_for

# 2024-06-12T14:00:00Z: a fixed scenario start so that files never depend on the wall clock.
DEFAULT_START_TIME = 1718200800.0

FLAVOURS = ("ardupilot", "px4")
SEABED_TYPES = ("sand", "mud", "shell", "gravel", "objects")
GNSS_KINDS = ("m8n", "rtk")


@dataclass(frozen=True)
class OysterBed:
    """A rectangular oyster bed of a farm (local frame, metres; bearing of its long side)."""

    centre_east_m: float
    centre_north_m: float
    length_m: float
    width_m: float
    bearing_deg: float
    clumps_per_m2: float
    row_spacing_m: float = 0.0
    """Above 0: the clumps are planted in rows along the bed's long side, this far apart
    (metres), instead of scattered."""
    clump_spacing_m: float = 0.0
    """Spacing of the clumps along a row (metres; used with ``row_spacing_m``)."""


@dataclass(frozen=True)
class QuadratArray:
    """One more 2 x 4 quadrat array (local frame, metres; grid bearing of its rows)."""

    centre_east_m: float
    centre_north_m: float
    row_bearing_deg: float
    pvc_side: str = "right"


@dataclass(frozen=True)
class Rack:
    """A farm rack (trestle) lying on the bed: ``n_rows`` parallel steel bars
    ``length_m`` long along grid bearing ``bearing_deg``, ``row_spacing_m`` apart, tied by
    cross bars every ``tie_spacing_m`` (0: none). Local frame, metres; the bars are
    ``bar_width_m`` wide and stand ``bar_height_m`` proud of the sand crests they rest on."""

    centre_east_m: float
    centre_north_m: float
    bearing_deg: float
    length_m: float
    n_rows: int
    row_spacing_m: float = 1.0
    tie_spacing_m: float = 2.0
    bar_width_m: float = 0.03
    bar_height_m: float = 0.05


@dataclass(frozen=True)
class Scenario:
    """Everything a simulated survey depends on, besides the seed."""

    name: str
    description: str
    origin_lat_deg: float
    """WGS84 latitude of the site origin (the local frame's origin, rounded to a UTM metre)."""
    origin_lon_deg: float
    start_time: float = DEFAULT_START_TIME
    """UNIX seconds (boat computer clock) of the first log record."""

    # --- Earth's field at the site (WMM-like values for the Chesapeake Bay, 2024) ---
    declination_deg: float = -10.9
    """Magnetic declination, east of true north (degrees)."""
    inclination_deg: float = 65.6
    """Magnetic inclination, downwards (degrees)."""
    field_mgauss: float = 519.0
    """Total field intensity (milligauss)."""

    # --- water and seabed ---
    water_depth_m: float = 1.2
    """Depth of the seabed's mean plane below the still water surface at the local origin."""
    seabed_slope_east: float = 0.002
    """Increase of depth per metre east (m/m): a gently sloping bed."""
    seabed_slope_north: float = -0.003
    """Increase of depth per metre north (m/m)."""
    seabed_type: str = "sand"
    """What the bottom is (``SEABED_TYPES``; ``tools.sim.bottoms``): "sand" (rippled sand
    with mud and shell patches), "mud" (soft mud/silt: dark, faint texture, no ripples),
    "shell" (shell hash over muddy sand, little ripple), "gravel" (gravel and cobble
    patches among the sand) or "objects" (smooth mud with sparse tyres, blocks, debris
    and clumps)."""
    soft_mud_reflectivity: float = 0.12
    """Mean reflectivity of a soft mud/silt bottom ("mud", "objects"): about 4.5 dB below
    the sand's 0.34 (fine, porous sediment scatters 5-10 dB less than sand near 1 MHz)."""
    undulation_amplitude_m: float = 0.0
    """Amplitude of the bed's long-wavelength undulation about the mean plane (metres; 0:
    none): a shore's profile is not a plane (``bathymetry``)."""
    undulation_wavelength_m: float = 20.0
    """Its main wavelength (metres, 10-40)."""
    undulation_bearing_deg: float = 0.0
    """Grid bearing of its main wave vector (the crests run across it)."""
    tide_rate_mps: float = 0.0
    """The water level's rate of rise (m/s; negative: falling; 0.3 m/h = 8.3e-5 m/s). The
    boat floats, so the sonar head and the echosounder rise with it."""
    seabed_resolution_m: float = 0.01
    """Cell size of the reflectivity and height maps (metres); made coarser (2, 3, 4 cm)
    when the map would exceed ``seabed_max_cells`` (``survey.seabed_resolution``)."""
    seabed_max_cells: int = 40_000_000
    """Cells the seabed maps may have: painting them peaks at about 35 bytes a cell (the
    hectare's 31 million cells: ~1.1 GB), so 40 million keeps a survey within ~1.5 GB."""
    seabed_margin_m: float = 1.0
    """Map margin beyond the farthest point the sonar can see (metres)."""
    sand_reflectivity: float = 0.34
    """Mean reflectivity of the sand (0..1; the truth GeoTIFF stores 255 * reflectivity)."""
    ripple_wavelength_m: float = 0.32
    """Mean crest-to-crest distance of the main ripple train (metres)."""
    ripple_amplitude_m: float = 0.008
    """Half the crest-to-trough height of the main sand ripples (metres)."""
    ripple_bearing_deg: float = 35.0
    """Mean grid bearing of the main train's wave vector (crests run perpendicular to it)."""
    ripple_bend_deg: float = 12.0
    """RMS turn of the crests across the site (degrees): the wave vector of each train is
    ``k (u + grad warp)``, the warp a sum of long plane waves (``seabed`` doc); the local
    wavelength varies by about half as much (a fraction ``tan(bend) / 2``)."""
    ripple_bend_scale_m: float = 12.0
    """Typical distance over which the crests turn (metres)."""
    ripple2_wavelength_m: float = 0.75
    """Mean wavelength of the second, superposed ripple train (metres)."""
    ripple2_amplitude_m: float = 0.004
    ripple2_bearing_deg: float = 110.0
    n_mud_patches: int = 2
    """Patches of smooth mud (little texture, almost no relief) on the survey area."""
    mud_reflectivity: float = 0.24
    n_shell_patches: int = 6
    scattered_clumps_per_m2: float = 0.02
    """Oyster clumps scattered over the whole map (per square metre)."""
    oyster_beds: tuple[OysterBed, ...] = ()
    oysters_per_quadrat: int = 9
    racks: tuple[Rack, ...] = ()

    # --- the 2 x 4 quadrat array (paper, Sec. IV-A-2) ---
    quadrat_centre_east_m: float = 0.0
    quadrat_centre_north_m: float = 0.0
    quadrat_row_bearing_deg: float = 78.0
    """Grid bearing of the rows (the line through the frame centres of a row)."""
    quadrat_pvc_side: str = "right"
    """Which side of the row axis (looking along the row bearing) the PVC row lies on."""
    quadrat_arrays: tuple[QuadratArray, ...] = ()
    """Further arrays beyond the one above (which is array 0)."""

    # --- survey (lawnmower) and boat motion ---
    survey_centre_east_m: float = 0.0
    survey_centre_north_m: float = 0.0
    lane_bearing_deg: float = 0.0
    """Grid bearing of the first lane; lanes alternate direction; the next lane lies to the
    right of the first."""
    lane_length_m: float = 16.0
    """Lane length (metres): at 0.4 m/s a neighbouring lane sees the same seabed again
    about 15-90 s later."""
    lane_spacing_m: float = 4.0
    n_lanes: int = 3
    skip_lanes: tuple[int, ...] = ()
    """Lanes (numbered from 0 across) the mission plans but the boat does not drive (a
    waypoint skipped, a lane cut short by the operator): the stripe of seabed between
    the lanes either side is left out (``trajectory.lawnmower``)."""
    run_in_m: float = 2.0
    """Straight approach before the first lane and after the last (metres)."""
    turn_radius_m: float = 2.0
    speed_mps: float = 0.4
    """Survey speed through the water (m/s): a small survey boat runs 0.3-0.5 m/s."""
    accel_time_s: float = 4.0
    """Time to reach the survey speed from rest, and to stop at the end (seconds)."""
    speed_wobble: float = 0.04
    """Relative standard deviation of the speed about its set point."""
    cross_track_m: float = 0.08
    """Standard deviation of the autopilot's cross-track error (metres; drawn 0.04-0.15)."""
    current_mps: float = 0.0
    """Water current speed (m/s); the boat crabs into it to hold its track."""
    current_toward_deg: float = 90.0
    """Grid bearing the current flows toward."""
    yaw_wobble_deg: float = 2.0
    """Standard deviation of the heading oscillation about the crab-corrected course
    (drawn 1-3)."""
    roll_deg: float = 2.5
    """Standard deviation of the wave-induced roll (a small boat in a light chop: drawn
    2-3)."""
    pitch_deg: float = 2.2
    """Standard deviation of the wave-induced pitch (drawn 2-3)."""
    trim_deg: float = 1.0
    """Bow-up pitch at survey speed."""
    heave_m: float = 0.03
    """Standard deviation of the wave-induced heave (metres; drawn 0.02-0.05)."""
    wave_period_s: float = 2.5
    """Dominant period of the short chop (seconds; drawn 2-3); the roll, pitch and heave
    are sums of sinusoids of 0.7-1.6 times it, kept within 1.5-4 s, random phases."""
    antenna_height_m: float = 0.10
    """Height of the GPS antenna (the vehicle reference point) above the waterline."""

    # --- sonar (Oculus M1200d, low-frequency mode) ---
    n_beams: int = 512
    fan_deg: float = 130.0
    beam_edge_ratio: float = 1.3
    """Bearing spacing at the fan edges over that at the centre (the real table is denser
    in the centre)."""
    horizontal_beamwidth_deg: float = 0.6
    """-3 dB width of one beam (the across-beam blur)."""
    vertical_aperture_deg: float = 20.0
    """-3 dB full width of the two-way vertical beam pattern."""
    range_m: float = 5.0
    range_resolution_m: float = 0.01
    ping_rate_hz: float = 5.0
    """Pings per second (the Oculus' 2, 5, 10, 15 or 40 Hz; any rate 0.5-40 works)."""
    ping_jitter_s: float = 0.002
    """Standard deviation of the sonar's ping interval jitter."""
    sonar_latency_s: float = 0.07
    """Delay from the ping's acquisition to its receive stamp on the boat computer
    (seconds: the sonar's processing, Ethernet, the driver; drawn 0.03-0.12)."""
    sonar_latency_jitter_s: float = 0.004
    """Mean of the exponential random part added to that delay, per ping (seconds)."""
    mount_x_m: float = -0.45
    mount_y_m: float = 0.0
    mount_z_m: float = 0.3
    mount_yaw_deg: float = 0.0
    tilt_deg: float = 15.0
    master_mode: int = 1
    frequency_hz: float = 1.2e6
    gain_percent: float = 50.0
    gamma: int = 127
    """Gamma correction byte (127 ~ exponent 0.5) applied before 8-bit quantisation."""
    ping_layout: int = 2
    """The SimplePingResult layout the sonar sends (its firmware): 2, with the sonar's
    heading, pitch and roll, or 1 (older firmware), whose pings say msgVersion 0 as the
    real ones do (PROTOCOLS.md; ``wide`` days: 1 a third of the days)."""
    sample_bits: int = 8
    """The image's samples: 8, or 16 (the fire's 16-bit flag: the same echo through the
    same gamma quantised 257 times finer; ``wide`` days: 16 a third of the days)."""
    gain_rows: bool = True
    """Each image row prefixed by its 4-byte gain word (the fire's send-gain flag; without
    it the gain assist's level is in the pixels and nowhere else; ``wide`` days: off a
    third of the days)."""
    speed_of_sound_mps: float = 1510.0
    salinity_ppt: float = 12.0
    water_temperature_c: float = 24.0
    full_scale: float = 0.25
    """Linear echo intensity that maps to pixel 255 (before gamma)."""
    noise_floor: float = 0.0008
    """Mean additive noise intensity (linear; ~14 after gamma and 8 bits)."""
    speckle_shape: float = 1.5
    """Gamma shape of the multiplicative speckle (1 = fully developed, Rayleigh amplitude)."""
    tvg_residual_exponent: float = 0.5
    """The sonar's TVG leaves intensity * (range / 2.5 m) ** exponent (not in the gains)."""
    tvg_step_db: float = 0.75
    """The TVG gain is applied in steps of this many dB: a sawtooth of ring artefacts."""
    row_gain_jitter_db: float = 0.2
    """Standard deviation of a fixed per-row gain error (more rings)."""
    gain_assist_db: float = 0.5
    """Standard deviation of the per-ping automatic gain change."""

    # --- downward echosounder (a Ping2-class altimeter on the autopilot) ---
    echosounder: bool = False
    """A downward echosounder reports DISTANCE_SENSOR (and RANGEFINDER on ArduPilot)."""
    echosounder_x_m: float = 0.2
    """Transducer offset from the antenna, body forward (metres)."""
    echosounder_y_m: float = 0.15
    """Starboard (metres)."""
    echosounder_z_m: float = 0.3
    """Down (metres): its face 0.2 m below the waterline with the antenna 0.1 m above."""
    echosounder_rate_hz: float = 8.0
    """Soundings per second (a Ping2 pings 5-10 times a second at these depths)."""
    echosounder_beam_deg: float = 30.0
    """Full -3 dB cone of the transducer (a Ping2's 115 kHz beam is about 30 degrees): it
    reports the nearest bottom inside it."""
    echosounder_noise_m: float = 0.01
    """Range noise, constant part (metres; 1 sigma)."""
    echosounder_noise_fraction: float = 0.005
    """Range noise, part proportional to the range (0.5 %: its range resolution)."""
    echosounder_dropout: float = 0.03
    """Fraction of the time the bottom is lost (aerated water behind the hull, a turn):
    runs of ~1 s with no reading or a reading flagged with signal quality 1."""
    echosounder_false_rate: float = 0.005
    """Fraction of soundings that lock on weed or a fish: a short range, fair quality."""
    echosounder_lag_s: float = 0.05
    """From the sounding's ping to its message's time_boot_ms (processing and the serial
    link at 115200 baud), seconds."""

    # --- navigation sensors ---
    flavour: str = "ardupilot"
    """Autopilot: "ardupilot" (RAW_IMU, ArduPilot scaling) or "px4" (HIGHRES_IMU, SI)."""
    imu_rate_hz: float = 55.0
    gps_rate_hz: float = 2.0
    heading_rate_hz: float = 2.0
    """Rate of ATTITUDE, GLOBAL_POSITION_INT and VFR_HUD (the compass-like heading)."""
    gps_bias_sigma_m: float = 1.2
    """Standard deviation of the wandering GPS error, per axis (metres; first-order
    Gauss-Markov; a u-blox M8N with a patch antenna: drawn 1.0-1.5)."""
    gps_bias_tau_s: float = 45.0
    """Correlation time of that error (seconds; drawn 20-90)."""
    gps_noise_m: float = 0.6
    """White GPS noise per axis (metres; drawn 0.5-0.8)."""
    gps_lag_s: float = 0.15
    """Age of a fix at its stamp: it reports where the antenna was this long before
    (seconds; the receiver's solution and serial latency: drawn 0.1-0.2)."""
    gps_outage_start_s: float | None = None
    """A GNSS outage (no fix) starting this long after the log start (seconds, at least
    1); None: no outage."""
    gps_outage_duration_s: float = 20.0
    gps_vertical_sigma_m: float = 1.5
    gnss_kind: str = "m8n"
    """The receiver (``GNSS_KINDS``): "m8n" (the u-blox M8N's metre-level fixes above) or
    "rtk" (a dual-frequency RTK receiver with a base: the ``rtk_*`` fields, fix_type 6,
    dropping to RTK float, fix_type 5, now and then)."""
    rtk_noise_m: float = 0.015
    """RTK fixed: white noise per axis (metres; drawn 0.01-0.02)."""
    rtk_bias_sigma_m: float = 0.008
    """RTK fixed: the slowly wandering error per axis (metres; Gauss-Markov; drawn
    0.005-0.012: multipath and the base's own error)."""
    rtk_bias_tau_s: float = 120.0
    """Its correlation time (seconds; drawn 60-300)."""
    rtk_vertical_sigma_m: float = 0.02
    """RTK fixed: vertical error (metres; about twice the horizontal)."""
    rtk_lag_s: float = 0.03
    """Age of an RTK fix at its stamp (seconds; drawn 0.02-0.05: a faster receiver and a
    faster link than the M8N's)."""
    rtk_float_interval_s: float = 150.0
    """Mean time between drops to RTK float (seconds; an exponential gap: a bridge, a
    tree line, the base's radio link fading)."""
    rtk_float_duration_s: float = 6.0
    """Mean length of a drop to float (seconds; drawn 2-3 times that spread)."""
    rtk_float_sigma_m: float = 0.2
    """RTK float: the error per axis while the ambiguities are not fixed (metres)."""
    compass_bias_deg: float = 2.0
    """Constant part of the heading error (degrees: mounting misalignment and the
    uncompensated field; drawn +-1-5)."""
    compass_deviation_1_deg: float = 1.0
    """Amplitude of the one-cycle (hard-iron) deviation ``sin(psi + phase_1)`` of the
    magnetic heading psi (degrees; drawn 0.5-2)."""
    compass_deviation_1_phase_deg: float = 30.0
    compass_deviation_2_deg: float = 0.8
    """Amplitude of the two-cycle (soft-iron) deviation ``sin(2 psi + phase_2)``
    (degrees; drawn 0.5-2)."""
    compass_deviation_2_phase_deg: float = 200.0
    compass_bias_wander_deg: float = 0.3
    """Slow wander of the bias (degrees; Gauss-Markov, ``compass_bias_tau_s``)."""
    compass_bias_tau_s: float = 600.0
    compass_gm_sigma_deg: float = 1.0
    """Correlated heading noise of the autopilot's fused heading (degrees; Gauss-Markov:
    drawn 0.5-1.5), not in the raw magnetometer."""
    compass_gm_tau_s: float = 8.0
    """Its correlation time (seconds; drawn 2-20)."""
    compass_noise_deg: float = 0.2
    """White noise of the reported heading (degrees; drawn 0.1-0.3)."""
    attitude_noise_deg: float = 0.3
    """Noise of the reported roll and pitch (degrees)."""
    accel_noise_mps2: float = 0.08
    accel_bias_sigma_mps2: float = 0.05
    gyro_noise_dps: float = 0.15
    gyro_bias_x_dps: float = 0.12
    """Gyro bias left after the autopilot's boot calibration, FRD x (degrees/s; drawn
    +-0.05-0.3 per axis)."""
    gyro_bias_y_dps: float = -0.08
    gyro_bias_z_dps: float = 0.15
    gyro_bias_sigma_dps: float = 0.2
    """Typical size of the gyro bias: the scale of its slow wander (``imu_bias_wander``)."""
    imu_bias_wander: float = 0.2
    """Slow wander of each IMU bias, as a fraction of its sigma (Gauss-Markov, 300 s)."""
    mag_noise_mgauss: float = 3.0
    stamp_delay_s: float = 0.002
    """Fixed part of the telemetry link delay (autopilot to boat computer)."""
    stamp_jitter_s: float = 0.002
    """Mean of the exponential random part of the telemetry link delay."""
    gcs_heartbeat_period_s: float = 1.0
    autopilot_uptime_s: float = 183.4
    """Autopilot uptime at the scenario start (time_boot_ms starts there)."""
    sonar_uptime_s: float = 612.0
    """Sonar uptime at the scenario start (pingStartTime, ping ids)."""

    # --- cutting a survey short (fast tests) ---
    duration_s: float | None = None
    max_pings: int | None = None

    # --- the field day ---
    wide: bool = False
    """With ``randomise``: also draw the site and the survey's set-up (seabed type, slope,
    undulation, tide, depth, range, tilt, speed, ping rate, echosounder, GNSS kind, the
    lanes; ``tools.sim.fieldday.WIDE_DAY``) from a separate stream of the seed."""
    randomise: bool = True
    """Draw the day's values (``tools.sim.fieldday.FIELD_DAY``) from the seed; false: the
    values above, exactly."""
    explicit: tuple[str, ...] = ()
    """Fields the caller set (``resolve_scenario`` records its overrides here): never
    drawn."""

    @property
    def declination_rad(self) -> float:
        return math.radians(self.declination_deg)


CHESAPEAKE_HORN_POINT = (38.6010, -76.1340)
"""Choptank River off Horn Point (UMCES), Cambridge, MD: the paper's region, 3-4 ft deep."""
CHOPTANK_FARM = (38.6290, -76.2160)
"""Choptank River shallows near Castle Haven, MD: a stand-in oyster lease."""

QUADRATS = Scenario(
    name="quadrats",
    description=(
        "The paper's test site: a 2 x 4 array of aluminium and PVC quadrats on rippled sand "
        "with a few oysters and mud patches, surveyed with three 16 m lanes at 0.4 m/s and "
        "5 pings/s (about 15 m x 15 m, under 3 minutes)."
    ),
    origin_lat_deg=CHESAPEAKE_HORN_POINT[0],
    origin_lon_deg=CHESAPEAKE_HORN_POINT[1],
)

QUADRATS_CURRENT = dataclasses.replace(
    QUADRATS,
    name="quadrats-current",
    description=(
        "The quadrats survey in a 0.064 m/s cross-current: the boat crabs about 9 degrees, "
        "so its heading differs from its course over ground."
    ),
    current_mps=0.064,
    current_toward_deg=90.0,
)

FARM = Scenario(
    name="farm",
    description=(
        "An on-bottom oyster farm, 40 m x 30 m of lanes at 0.4 m/s (about 16 minutes): "
        "oyster beds (one planted in rows), scattered clumps, two racks of bars 1 m apart, "
        "shell and mud patches, two ripple trains, and three quadrat arrays."
    ),
    origin_lat_deg=CHOPTANK_FARM[0],
    origin_lon_deg=CHOPTANK_FARM[1],
    start_time=DEFAULT_START_TIME + 86400.0,
    water_depth_m=1.15,
    seabed_slope_east=0.003,
    seabed_slope_north=0.001,
    ripple_wavelength_m=0.28,
    ripple_bearing_deg=120.0,
    n_shell_patches=40,
    n_mud_patches=5,
    scattered_clumps_per_m2=0.08,
    oyster_beds=(
        OysterBed(-12.0, 6.0, 14.0, 6.0, 15.0, 3.0),
        OysterBed(6.0, 10.0, 12.0, 5.0, 100.0, 2.5, row_spacing_m=1.0, clump_spacing_m=0.5),
        OysterBed(-8.0, -8.0, 10.0, 7.0, 60.0, 2.0),
        OysterBed(14.0, -9.0, 9.0, 6.0, 170.0, 3.5),
    ),
    racks=(
        Rack(-4.0, -1.0, 90.0, 10.0, 5),
        Rack(2.0, -12.0, 0.0, 8.0, 4, tie_spacing_m=1.5),
    ),
    quadrat_centre_east_m=4.0,
    quadrat_centre_north_m=-1.0,
    quadrat_row_bearing_deg=70.0,
    quadrat_arrays=(
        QuadratArray(-3.0, 8.0, 0.0),
        QuadratArray(16.0, 2.0, 135.0, pvc_side="left"),
    ),
    lane_bearing_deg=90.0,
    lane_length_m=40.0,
    lane_spacing_m=4.0,
    n_lanes=8,
    current_mps=0.05,
    current_toward_deg=200.0,
)


def _lease_beds() -> tuple[OysterBed, ...]:
    """The hectare's beds: a 4 x 3 grid of 20 m x 6 m beds along grid north, 24 m apart
    east-west and 30 m north-south, densities varying bed to bed; the bed at (12, 0) is
    left out (the quadrat array lies near it, on clean sand)."""
    beds = []
    for i, east in enumerate((-36.0, -12.0, 12.0, 36.0)):
        for j, north in enumerate((-30.0, 0.0, 30.0)):
            if (east, north) == (12.0, 0.0):
                continue
            density = 1.5 + 0.5 * ((3 * i + j) % 4)
            beds.append(OysterBed(east, north, 20.0, 6.0, 5.0 * (j - 1), density))
    return tuple(beds)


HECTARE = Scenario(
    name="hectare",
    description=(
        "A hectare of on-bottom oyster lease for long-run benchmarks: eleven oyster beds in "
        "rows, scattered clumps, shell patches, ripples and the quadrat array, surveyed with "
        "34 lanes of 100 m, 2.8 m apart, at 0.5 m/s (about 2 h, 71,000 pings at 10 Hz). "
        "Seabed cells are 2 cm (31 million cells, about 155 MB) instead of 1 cm (10^8). "
        "Meant to be streamed (tools.sim.stream); simulate needs max_pings or duration_s."
    ),
    origin_lat_deg=CHOPTANK_FARM[0],
    origin_lon_deg=CHOPTANK_FARM[1],
    start_time=DEFAULT_START_TIME + 2 * 86400.0,
    water_depth_m=1.25,
    seabed_slope_east=0.0015,
    seabed_slope_north=-0.001,
    seabed_resolution_m=0.02,
    ripple_wavelength_m=0.30,
    ripple_bearing_deg=60.0,
    n_shell_patches=150,
    n_mud_patches=12,
    scattered_clumps_per_m2=0.05,
    oyster_beds=_lease_beds(),
    quadrat_centre_east_m=12.0,
    quadrat_centre_north_m=2.0,
    quadrat_row_bearing_deg=70.0,
    lane_bearing_deg=0.0,
    lane_length_m=100.0,
    lane_spacing_m=2.8,
    n_lanes=34,
    turn_radius_m=1.4,
    speed_mps=0.5,
    ping_rate_hz=10.0,
    current_mps=0.05,
    current_toward_deg=200.0,
)

SHORE = dataclasses.replace(
    QUADRATS,
    name="shore",
    description=(
        "The quadrats on a sloping shore: the bed deepens 6.25 % to the east, across five "
        "16 m lanes 4 m apart, so the sonar runs 1.1-2.1 m above it; a downward echosounder "
        "beside the antenna (DISTANCE_SENSOR and RANGEFINDER), ArduPilot, an M8N (about "
        "4.5 minutes)."
    ),
    water_depth_m=1.8,
    seabed_slope_east=0.0625,
    seabed_slope_north=0.0,
    n_lanes=5,
    lane_spacing_m=lane_spacing_for(5.0, 1.6, 15.0, 130.0, 20.0),
    echosounder=True,
)

MUD = dataclasses.replace(
    QUADRATS,
    name="mud",
    description=(
        "The quadrats on soft mud: a dark bottom with faint fine texture, no ripples and "
        "very few clumps (about 3 minutes)."
    ),
    seabed_type="mud",
)

DEEP = dataclasses.replace(
    QUADRATS,
    name="deep",
    description=(
        "The quadrats in 3.5 m of water: 10 m range (600 lines of 1.67 cm), 25 degrees "
        "tilt, 10 pings/s, 0.9 m/s, three 48 m lanes spaced to the wider swath (about "
        "3.3 minutes)."
    ),
    water_depth_m=3.5,
    range_m=10.0,
    range_resolution_m=range_resolution_for(10.0),
    tilt_deg=25.0,
    ping_rate_hz=10.0,
    speed_mps=0.9,
    lane_length_m=48.0,
    lane_spacing_m=lane_spacing_for(10.0, 3.3, 25.0, 130.0, 20.0),
    turn_radius_m=3.0,
)

RTK = dataclasses.replace(
    QUADRATS,
    name="rtk",
    description=(
        "The quadrats with an RTK receiver (fixes at 5 Hz, 1-2 cm, now and then a few "
        "seconds of RTK float) and a compass 3 degrees off (about 3 minutes)."
    ),
    gnss_kind="rtk",
    gps_rate_hz=5.0,
    compass_bias_deg=3.0,
    explicit=("compass_bias_deg",),
)

FIELD = dataclasses.replace(
    QUADRATS,
    name="field",
    description=(
        "The quadrats on a field day drawn wide from the seed: seabed type, slope, "
        "undulation, tide, depth, range, tilt, speed, ping rate, echosounder, GNSS kind "
        "and lanes (tools.sim.fieldday.WIDE_DAY; about 3-5 minutes)."
    ),
    wide=True,
)

SCENARIOS: dict[str, Scenario] = {
    s.name: s for s in (QUADRATS, FARM, QUADRATS_CURRENT, HECTARE, SHORE, MUD, DEEP, RTK, FIELD)
}

STREAM_ONLY: frozenset[str] = frozenset({HECTARE.name})
"""Scenarios too long to write whole: ``simulate`` needs ``max_pings`` or ``duration_s``
for them (``tools.sim.stream`` streams them in memory instead)."""


def _check_value(name: str, value: Any, annotation: Any) -> Any:
    """Check an override against the field's type; ints are accepted for floats."""
    args = typing.get_args(annotation)
    if type(None) in args:
        if value is None:
            return None
        annotation = next(a for a in args if a is not type(None))
    if annotation is float and isinstance(value, int | float) and not isinstance(value, bool):
        if not math.isfinite(value):
            raise SeamapError(f"simulate: {name} must be finite, got {value!r}")
        return float(value)
    if annotation is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if annotation is str and isinstance(value, str):
        return value
    if annotation is bool and isinstance(value, bool):
        return value
    if annotation == tuple[int, ...]:
        if isinstance(value, list | tuple) and all(
            isinstance(v, int) and not isinstance(v, bool) for v in value
        ):
            return tuple(value)
        raise SeamapError(f"simulate: {name} = {value!r} is not a list of integers")
    if typing.get_origin(annotation) in (tuple, dict):
        return value
    raise SeamapError(
        f"simulate: {name} = {value!r} is not a {getattr(annotation, '__name__', annotation)}"
    )


def resolve_scenario(name: str, **overrides: Any) -> Scenario:
    """The named scenario with overrides applied; a bad name, key or value is a SeamapError."""
    try:
        base = SCENARIOS[name]
    except KeyError:
        raise SeamapError(
            f"simulate: unknown scenario {name!r} (known: {', '.join(SCENARIOS)})"
        ) from None
    hints = typing.get_type_hints(Scenario)
    checked: dict[str, Any] = {}
    for key, value in overrides.items():
        if key not in hints or key in ("name", "description", "explicit"):
            raise SeamapError(f"simulate: unknown override {key!r}")
        checked[key] = _check_value(key, value, hints[key])
    pinned = tuple(sorted(set(base.explicit) | set(checked)))
    scenario = dataclasses.replace(base, **checked, explicit=pinned)
    _validate(scenario)
    return scenario


def parse_overrides(texts: dict[str, str]) -> dict[str, Any]:
    """Command-line overrides (``{"n_beams": "128", "flavour": "px4"}``) typed by the
    Scenario fields they name ("none" clears an optional field); SeamapError names a bad
    key or value. The result goes to ``resolve_scenario`` / ``simulate``."""
    hints = typing.get_type_hints(Scenario)
    values: dict[str, Any] = {}
    for key, text in texts.items():
        if key not in hints or key in _NOT_FROM_TEXT:
            raise SeamapError(f"simulate: unknown override {key!r}")
        args = typing.get_args(hints[key])
        optional = type(None) in args
        kind = next((a for a in args if a is not type(None)), hints[key])
        if optional and text.strip().lower() == "none":
            values[key] = None
            continue
        if hints[key] == tuple[int, ...]:  # a comma-separated list, e.g. skip_lanes=2,5
            try:
                values[key] = tuple(int(part) for part in text.split(",") if part.strip())
            except ValueError:
                raise SeamapError(f"simulate: {key} = {text!r} is not a list of integers") from None
            continue
        try:
            values[key] = kind(text) if kind in (int, float, str) else None
        except ValueError:
            raise SeamapError(f"simulate: {key} = {text!r} is not a {kind.__name__}") from None
        if kind is bool:
            if text.lower() not in ("true", "false"):
                raise SeamapError(f"simulate: {key} = {text!r} is not true or false")
            values[key] = text.lower() == "true"
    return values


_NOT_FROM_TEXT = ("name", "description", "explicit", "oyster_beds", "racks", "quadrat_arrays")


def _validate(s: Scenario) -> None:
    problems = []
    if s.flavour not in FLAVOURS:
        problems.append(f"flavour {s.flavour!r} is not one of {', '.join(FLAVOURS)}")
    if not 2 <= s.n_beams <= 1024:
        problems.append(f"n_beams {s.n_beams} is not in 2..1024")
    if not 0.001 <= s.range_resolution_m <= s.range_m / 8:
        problems.append(f"range_resolution_m {s.range_resolution_m} does not fit range {s.range_m}")
    if not 0.5 <= s.ping_rate_hz <= 40.0:
        problems.append(f"ping_rate_hz {s.ping_rate_hz} is not in 0.5..40")
    if s.max_pings is not None and s.max_pings < 1:
        problems.append(f"max_pings {s.max_pings} must be at least 1")
    if s.duration_s is not None and s.duration_s <= 0:
        problems.append(f"duration_s {s.duration_s} must be positive")
    if s.current_mps < 0 or s.current_mps >= 0.8 * s.speed_mps:
        problems.append(f"current_mps {s.current_mps} must be in [0, 0.8 * speed_mps)")
    if min(s.sonar_latency_s, s.sonar_latency_jitter_s, s.gps_bias_sigma_m, s.gps_noise_m) < 0:
        problems.append("latencies and GPS error sizes must not be negative")
    if not 0.0 <= s.gps_lag_s < 1.0 or s.gps_bias_tau_s <= 0 or s.compass_gm_tau_s <= 0:
        problems.append("gps_lag_s must be in [0, 1) and the correlation times positive")
    if s.gps_outage_start_s is not None and (
        s.gps_outage_start_s < 1.0 or s.gps_outage_duration_s <= 0
    ):
        problems.append("a GNSS outage needs a start >= 1 s (after a fix) and a duration")
    if s.wave_period_s <= 0 or s.ripple_wavelength_m <= 0 or s.ripple2_wavelength_m <= 0:
        problems.append("wave periods and ripple wavelengths must be positive")
    if s.lane_spacing_m <= 0 or s.n_lanes < 1 or s.lane_length_m <= 0:
        problems.append("the lawnmower needs n_lanes >= 1 and positive lane length and spacing")
    if any(not 0 <= lane < s.n_lanes for lane in s.skip_lanes):
        problems.append(f"skip_lanes {list(s.skip_lanes)}: lanes are 0 to {s.n_lanes - 1}")
    elif len(set(s.skip_lanes)) >= s.n_lanes:
        problems.append("skip_lanes leaves no lane to drive")
    if not 0.0 < s.tilt_deg < 60.0:
        problems.append(f"tilt_deg {s.tilt_deg} is not in (0, 60)")
    if s.seabed_type not in SEABED_TYPES:
        problems.append(f"seabed_type {s.seabed_type!r} is not one of {', '.join(SEABED_TYPES)}")
    if s.ping_layout not in (1, 2):
        problems.append(f"ping_layout {s.ping_layout} is not 1 or 2 (SimplePingResult v1/v2)")
    if s.sample_bits not in (8, 16):
        problems.append(f"sample_bits {s.sample_bits} is not 8 or 16")
    if s.gnss_kind not in GNSS_KINDS:
        problems.append(f"gnss_kind {s.gnss_kind!r} is not one of {', '.join(GNSS_KINDS)}")
    if abs(s.tide_rate_mps) > 1e-3:
        problems.append(f"tide_rate_mps {s.tide_rate_mps} is beyond +-1e-3 m/s (3.6 m/h)")
    if not 0.0 <= s.undulation_amplitude_m <= 0.5 or s.undulation_wavelength_m < 2.0:
        problems.append("undulation_amplitude_m must be in [0, 0.5], its wavelength >= 2 m")
    if abs(s.seabed_slope_east) > 0.3 or abs(s.seabed_slope_north) > 0.3:
        problems.append("seabed slopes beyond 0.3 are not a survey site")
    if s.echosounder and not (
        0.5 <= s.echosounder_rate_hz <= 50.0 and 0.0 < s.echosounder_beam_deg < 90.0
    ):
        problems.append("the echosounder needs a rate in 0.5..50 Hz and a cone in (0, 90) deg")
    if not 0.0 <= s.echosounder_dropout < 1.0 or not 0.0 <= s.echosounder_false_rate < 1.0:
        problems.append("echosounder_dropout and echosounder_false_rate must be in [0, 1)")
    if s.rtk_float_interval_s <= 0 or s.rtk_float_duration_s < 0 or s.rtk_bias_tau_s <= 0:
        problems.append("rtk_float_interval_s and rtk_bias_tau_s must be positive")
    if not 0.0 <= s.rtk_lag_s < 1.0:
        problems.append("rtk_lag_s must be in [0, 1)")
    if s.seabed_max_cells < 1_000_000:
        problems.append("seabed_max_cells must be at least a million")
    if problems:
        raise SeamapError(f"simulate {s.name}: " + "; ".join(problems))


def scenario_dict(s: Scenario) -> dict[str, Any]:
    """The scenario as JSON-ready data (for truth.json)."""
    data = dataclasses.asdict(s)
    data["oyster_beds"] = [dataclasses.asdict(b) for b in s.oyster_beds]
    data["racks"] = [dataclasses.asdict(r) for r in s.racks]
    data["quadrat_arrays"] = [dataclasses.asdict(a) for a in s.quadrat_arrays]
    data["explicit"] = list(s.explicit)
    return data
