"""The seabed under the boat, ping by ping: the sonar's altitude and the bottom's slope.

A fixed ``altitude_m`` for a whole survey is wrong on any sloping shore and through a
tide, and a wrong altitude is a wrong ground range everywhere in the fan. This module
gives, for each ping, the plane of the seabed under the sonar, from the best source there
is: a downward echosounder's soundings (``RangeSample``) placed in the local frame by
the navigation, else the configured altitude on a level bed.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class EchosounderMount:
    """Where a downward echosounder's transducer sits on the vehicle (body FRD, metres
    from the GPS antenna), and the span of distances it reports validly (metres)."""

    forward_m: float = 0.0
    starboard_m: float = 0.0
    down_m: float = 0.3
    min_distance_m: float = 0.3
    max_distance_m: float = 100.0


@dataclass(frozen=True, slots=True)
class BottomParams:
    """How the seabed under each ping is found."""

    use_echosounder: bool = True
    """Take the altitude and slope from a downward echosounder's soundings when the
    navigation log has them (else the configured altitude, level)."""
    echosounder: EchosounderMount = EchosounderMount()
