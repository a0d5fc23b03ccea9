"""The live engine's settings (``StreamingParams``), in a module of their own so that the
engine (``mapping.streaming``) and its stages (``mapping.stream_*``) all take them from
below."""

from __future__ import annotations

from dataclasses import dataclass, field

from mapping.live_anchor import AnchorParams
from mapping.live_closures import LiveClosureParams
from mapping.live_resolve import ResolveParams
from mapping.pipeline import Mode, PipelineParams


@dataclass(frozen=True, slots=True)
class StreamingParams:
    pipeline: PipelineParams = field(default_factory=PipelineParams)
    reorder_s: float = 0.25
    """Samples are held this long (survey time) to be put in time order."""
    window_frames: int = 30
    """Accepted frames re-optimised together (3 s at 10 Hz): a fixed-lag smoother over
    the last six GPS fixes. Longer windows move frames further between their first
    blend and their final pose, so more of them are blended twice."""
    solve_every: int = 10
    """Re-solve the window every this many accepted frames."""
    move_threshold_m: float = 0.02
    """A frame whose fan has moved more than this (a mosaic pixel) since it was blended
    is re-blended when its pose becomes final."""
    live_move_threshold_m: float = 0.25
    """While in the window, a frame is re-blended only when it moved more than this: the
    window's solution shifts with every GPS fix by a centimetre or two, and chasing each
    shift would re-blend every frame at every solve."""
    render_every_s: float = 0.5
    """New coverage is rendered at most this often (survey time): a ping shows within
    ``reorder_s`` plus this."""
    refine_every_s: float = 1.5
    """Pixels that already showed are re-rendered (refined by later frames) this often."""
    redraw_render_every_s: float = 6.0
    """Pixels a re-solve's redraws changed are rendered this often: a stretch's redraws
    go on over the same tiles for seconds, and rendered with every refine a pixel is
    blended again each time. Measured on quadrats seed 1 at 5 Hz (two runs each, against
    every 1.5 s): render 11.7 -> 10.4 ms a frame; nothing at 2 Hz, where most tiles a
    redraw touches leave memory, and are rendered then, before the next."""
    evict_after_s: float = 30.0
    """A tile no frame has touched for this long may leave memory."""
    tile_memory_mb: float | None = 256.0
    """Such idle tiles stay in memory, the least recently used leaving first, while the
    tiles take no more than this (None: idle tiles leave at once)."""
    live_registration_res_m: float | None = 0.03
    """Pixel size of the live registrations (None: the pipeline's). 3 cm halves the FFT
    work; the survey-end pass registers again at the pipeline's full resolution."""
    live_yaw_from_gyro: bool = True
    """The live registrations take each pair's turn from the gyro (where the filter's gyro
    joins the two frames) and search no rotation: the sectors' fit at the gyro's turn is
    the answer (``FmtParams.known_yaw_iterations``). The survey-end pass searches."""
    live_candidates: int | None = 8
    """Blending candidates each live tile keeps per pixel (None: the pipeline's
    ``top_n``, 16): half the slots to scan for each frame offered and half the memory of
    a tile; the survey-end pass keeps the pipeline's."""
    front_depth: int = 4
    """Pings the front stage (``mapping.stream_front``) may hold beyond the frames the
    stages after it have chained: it works that far ahead in a worker process. The
    soundings that place a ping's seabed are taken over the live poses this many frames
    back, wherever the front runs (so the map does not depend on where it runs): 0.4 s
    at 10 Hz, against a bottom model rebuilt every few seconds."""
    final_mode: Mode = Mode.SINGLE_STAGE
    """The survey-end pass: single-stage, or two-stage for long surveys."""
    closure_hold_frames: int = 100
    """While a pair of passes waits for agreeing closures, frames drawn since the last
    closure stay in the window, up to this many (10 s at 10 Hz; a live frame holds its
    image, score and mask, about 1 MB on a 5 m fan at 2 cm)."""
    anchor: AnchorParams = field(default_factory=AnchorParams)
    """How the live chain is tied to the GNSS and the heading filter."""
    closures: LiveClosureParams = field(default_factory=LiveClosureParams)
    """Live loop closures against keyframes of the final map."""
    resolve: ResolveParams = field(default_factory=ResolveParams)
    """The drawn map re-solved and redrawn every few seconds of survey."""
    resolve_tiles_in_memory: int = 16
    """While redrawing, tiles idle for ``evict_after_s`` leave memory once more than this
    many are loaded (5.2 MB each): a redraw over an old stretch loads its tiles."""
    bridge_velocity_age_s: float = 5.0
    """A frame the registration could not chain is bridged at the speed (vehicle frame)
    the registrations last measured when they measured it this recently, else by the
    filter's dead reckoning."""
    bridge_velocity_sigma_mps: float = 0.06
    """Error of such a bridge per second it spans: 9-16 cm over 2 s measured at a U-turn
    in a GNSS outage (quadrats seed 10, 2 Hz)."""
    bridge_filter_sigma_mps: float = 0.3
    """Error of a filter's dead-reckoned bridge per second: 50-80 cm over 2 s measured in
    a GNSS outage (the same survey), where the accelerometers alone carry the velocity."""
    heading_fresh_s: float = 1.0
    """The filter's heading is a measurement of the chain's for the anchor while the gyro
    has carried it without a break since the last compass heading, or this long after
    one: with the autopilot link silent the filter holds its heading whatever the boat
    does, and when the link returns the gyro comes back before the compass has spoken."""
    gnss_time_offset_s: float = 0.1
    """A fix shows the antenna this long before the frame stamps say (fix lag minus
    sonar latency)."""
    reuse_registrations: bool = False
    """The survey-end pass reuses the live registrations instead of registering every
    frame again against the smoothed EKF. Faster (no FMT at the end), but the live ones
    were guided by the live filter, so the result differs from an offline single-stage
    run by up to a centimetre; re-registering makes the two identical."""
