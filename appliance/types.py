"""Data passed between the stages, the service and the outputs (see DESIGN.md, data flow)."""

# Road-plane coordinates everywhere: metres, X across the road (+ to the right as seen from the
# camera), Y along the road (+ away from the camera). Times: `t` is capture time in monotonic
# seconds, `wall` is Unix wall-clock seconds.

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from enum import IntEnum
from typing import Protocol

import numpy as np


@dataclass(slots=True)
class Frame:
    """One grey frame from a source."""

    seq: int
    t: float
    wall: float
    image: np.ndarray  # uint8, H x W
    repeated: bool = False  # set by the source or the pipeline when identical to the previous frame


@dataclass(slots=True)
class VehicleState:
    """A vehicle as the tracker sees it at one frame (provisional while ``finished`` is False)."""

    id: int
    t: float
    x: float  # lateral road position: the middle (median) of its low features across the road (m)
    y_front: float  # along-road position of the vehicle's front in its direction of travel (m)
    y_rear: float  # along-road position of its rear (m)
    vx: float  # road velocity (m/s)
    vy: float
    length: float  # length estimate (m)
    n_features: int
    finished: bool = False  # True once, when the vehicle is finalised (see exited)
    # optional: its earlier (t, x, y_front) points, given with a vehicle's first report so that the
    # measures can count a line crossed before the vehicle was reported
    trajectory: list[tuple[float, float, float]] | None = None
    exited: bool = False  # finished at the exit zone (a vehicle lost after leaving the detection zone is
    # finished too, where it was last seen)
    # set on a vehicle's first report (and the states backfilled from it) when it was first seen in its lane's
    # detection zone, not where a vehicle was lost: if it already straddles its count line (a receding
    # vehicle entering over the image's bottom edge, its front far ahead) it counts there
    entered: bool = False
    # set on a vehicle's first report when the pipeline extended it back to its region's entry (the first point
    # of its trajectory is that extrapolated entry)
    backfilled: bool = False
    # along-road speed of its lowest features (m/s): the spot speed reported at count lines, presence loops and
    # in vehicle records (vy is its low part's, taking in parts higher up that move faster in projection); None: vy
    spot_vy: float | None = None
    # a young reported group being re-checked as a part of vehicle ``part_of`` (appliance.grouping, RECHECK_S):
    # the measures hold a count-line crossing of it until the check ends
    part_of: int | None = None
    # its last state (finished), when it has joined vehicle ``joined`` as a part of it: a crossing held for it is
    # dropped and its Edie distance and time are that vehicle's, counted once (NO_VEHICLE: it was none at all)
    joined: int | None = None


# VehicleState.joined of a reported group that turned out to be no vehicle at all: only a shadow on the road, or
# features stuck on it that a vehicle drove through. A crossing held for it is dropped and, if it never counted, its
# Edie distance and time in the periods still open are taken back (one that counted stands in for a vehicle: a
# shadow cast ahead of a car hidden until then counts in its place).
NO_VEHICLE = -2


@dataclass(slots=True)
class LoopEvent:
    """One actuation of a virtual loop, as a real inductive loop of that length would give it."""

    loop_id: str
    channel: int
    lane: int
    t_on: float  # monotonic capture time
    t_off: float
    wall_on: float
    wall_off: float
    speed_kmh: float | None
    length_m: float | None
    vehicle_id: int | None = None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(slots=True)
class VehicleRecord:
    """Summary of one ended vehicle: finished, or counted and then gone without a finish."""

    id: int
    lane: int
    wall_entry: float
    wall_exit: float
    speed_kmh: float
    length_m: float
    length_class: str
    lane_changes: int = 0
    trajectory: list[tuple[float, float, float]] | None = None  # (t, x, y_front) as reported

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(slots=True)
class LaneAggregate:
    """Per-lane measures over one period (Edie's generalised definitions over the lane region)."""

    lane: int
    period_start: float  # wall-clock, aligned to the period length
    period_s: float
    count: int
    flow_vph: float  # Edie q = d(A)/|A|
    density_vpkm: float  # Edie k = t(A)/|A|
    speed_kmh: float | None  # Edie space-mean v = d(A)/t(A)
    time_mean_speed_kmh: float | None
    occupancy_pct: float | None
    speed85_kmh: float | None
    headway_s: float | None  # mean headway at the count position
    class_counts: dict[str, int] = field(default_factory=dict)
    partial: bool = False  # the period was not fully observed (start-up, restart, outage)
    quality: int = 0  # bitfield of HealthFault values seen during the period

    def to_dict(self) -> dict:
        return asdict(self)


class HealthFault(IntEnum):
    """Named faults; the value is the bit number in the health bitfield."""

    CAMERA_LOST = 0
    FROZEN_IMAGE = 1
    TOO_DARK = 2
    HEAVY_SHAKE = 3
    FIDUCIALS_LOST = 4
    LOCKED_ON = 5
    NO_HITS = 6
    STORAGE = 7
    OVERLOAD = 8
    CONFIG = 9


@dataclass(slots=True)
class LoopSight:
    """What the image shows on a loop (appliance.presence): since when something has been on it (None: the
    road), and the standing call it gives: the times its vehicle came onto the loop and stood still there."""

    came: float | None = None
    standing: tuple[float, float] | None = None


@dataclass(slots=True)
class ChannelState:
    """What one detector channel (one virtual loop) shows the controller now."""

    channel: int
    loop_id: str
    lane: int
    call: bool  # presence (or pulse) call, after force-call and fail-safe are applied
    count: int  # never reset; outputs wrap it to 16 bits
    occupancy_pct: float  # over the current rolling window or the period so far
    last_speed_kmh: float | None
    last_length_m: float | None
    class_counts: dict[str, int] = field(default_factory=dict)
    forced: bool = False


@dataclass(slots=True)
class DetectorSnapshot:
    """Everything the controller outputs publish, taken once per frame by the service."""

    wall: float
    uptime_s: float
    channels: list[ChannelState]
    faults: int  # bitfield of HealthFault
    fps: float
    last_period: list[LaneAggregate]  # last complete period, one per lane (empty before the first)
    period_seq: int  # 0-255, incremented per completed period
    tracked_vehicles: int = 0
    dropped_frames: int = 0

    def has_fault(self, fault: HealthFault) -> bool:
        return bool(self.faults >> int(fault) & 1)


class FrameSource(Protocol):
    """A source of frames (drivers implement it). ``read`` returns None at end of stream."""

    def open(self) -> None: ...

    def read(self) -> Frame | None: ...

    def close(self) -> None: ...


class CommandSink(Protocol):
    """What outputs and the status interface may ask of the service."""

    def force_call(self, channel: int, seconds: float) -> None: ...


class Output(Protocol):
    """A controller output (Modbus TCP/RTU, serial line)."""

    def start(self, commands: CommandSink) -> None: ...

    def publish(self, snapshot: DetectorSnapshot, events: list[LoopEvent]) -> None: ...

    def stop(self) -> None: ...
