"""The Modbus register map, defined once here as data, and the pure encoding of a
DetectorSnapshot into discrete-input bits and input-register words (no I/O)."""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass, field
from importlib import metadata

import numpy as np

from appliance.config import SiteConfig
from appliance.types import DetectorSnapshot, HealthFault

MAP_VERSION = 1
MAX_CHANNELS = 256  # config allows channels 1..256
MAX_LANES = 32
MAX_CLASSES = 8
NO_DATA = 0xFFFF
FAULT_FLAG = 0xFF00  # occupancy register = FAULT_FLAG | NTCIP fault code while in fault
LANE_STRIDE = 24
MAX_READ_BITS = 2000  # Modbus application protocol limits per request
MAX_READ_REGS = 125
MAX_WRITE_REGS = 123

# 1-based ("Modicon") offsets per table, as many masters and PLC tools number them.
ONE_BASED = {"di": 10001, "ir": 30001, "hr": 40001}
TABLE_NAMES = {"di": "discrete input (FC 2)", "ir": "input register (FC 4)", "hr": "holding register (FC 3/6/16)"}

# NTCIP 1202 detector volume/occupancy fault values, and the health faults that raise them
# (first match wins). STORAGE and CONFIG faults do not make detector data invalid.
NTCIP_FAULTS: list[tuple[HealthFault, int, str]] = [
    (HealthFault.CAMERA_LOST, 212, "open loop fault (camera lost)"),
    (HealthFault.FROZEN_IMAGE, 216, "watchdog fault (frozen image)"),
    (HealthFault.OVERLOAD, 216, "watchdog fault (processing overload)"),
    (HealthFault.LOCKED_ON, 210, "max presence fault (locked-on call)"),
    (HealthFault.HEAVY_SHAKE, 214, "excessive change fault (heavy camera shake)"),
    (HealthFault.TOO_DARK, 217, "erratic output fault (image too dark)"),
    (HealthFault.FIDUCIALS_LOST, 217, "erratic output fault (fiducials lost)"),
    (HealthFault.NO_HITS, 211, "no activity fault"),
]


# Faults that put the calls in fail-safe (outputs.failsafe); the service applies them to the
# calls, the map reports them. Must equal appliance.service.FAILSAFE_FAULTS (a test checks).
FAILSAFE_FAULTS = (HealthFault.CAMERA_LOST, HealthFault.FROZEN_IMAGE, HealthFault.OVERLOAD)


@functools.cache
def firmware_version() -> tuple[int, int, int]:
    try:
        parts = metadata.version("roadwatch").split(".")
        nums = [int("".join(c for c in p if c.isdigit()) or 0) for p in parts[:3]]
    except metadata.PackageNotFoundError:
        nums = [0, 0, 0]
    return tuple((nums + [0, 0, 0])[:3])  # type: ignore[return-value]


def fault_code(faults: int) -> int:
    """NTCIP-1202-style fault code (210-217) for a HealthFault bitfield, 0 when data are valid."""
    for bit, code, _ in NTCIP_FAULTS:
        if faults >> int(bit) & 1:
            return code
    return 0


@dataclass(frozen=True)
class Field:
    """One entry of the map: a single value or an array indexed by channel, lane or class."""

    table: str  # "di", "ir", "hr"
    address: int  # 0-based wire address of the first element
    name: str
    type: str  # "bit", "uint16", "uint32" (uint32: high word first)
    unit: str
    scale: str  # how to get the unit from the raw value
    meaning: str
    per: str = ""  # "" single value, "channel" (element c-1 for channel c), "lane" (lane slot i)
    count: int = 1  # elements
    stride: int = 1  # addresses between elements

    @property
    def width(self) -> int:
        return 2 if self.type == "uint32" else 1

    def addr(self, index: int = 0) -> int:
        return self.address + index * self.stride

    @property
    def end(self) -> int:  # one past the last address used
        return self.addr(self.count - 1) + self.width


# --- the map --------------------------------------------------------------------------------
STATUS = 0
# every address stays below 9999 so the 5-digit 1-based notation (30001-39999) is unambiguous
CH_COUNT, CH_OCC, CH_SPEED, CH_LENGTH, CH_CLASS, CLASS_STRIDE = 1000, 1300, 1600, 1900, 2200, 300
PERIOD = 5000
LANES = 5100
DI_CALL, DI_FAULT, DI_FAILSAFE, DI_FORCED = 0, 1000, 1016, 2000
HR_FORCE = 0

_DEFAULT_CLASSES = ["motorcycle", "small", "medium", "large"]

MAP: list[Field] = [
    Field("di", DI_CALL, "call", "bit", "", "1 = call", "Live detector call of channel c (presence, held through a dropout shorter than 0.2 s as a detector card's dropout filter holds it, so one vehicle is one actuation; or a pulse of pulse_ms per actuation in pulse mode; force-call and fail-safe applied)", "channel", MAX_CHANNELS),
    *[
        Field("di", DI_FAULT + int(f), f"fault_{f.name.lower()}", "bit", "", "1 = active", f"Health fault {f.name}")
        for f in HealthFault
    ],
    Field("di", DI_FAULT + len(HealthFault), "fault_reserved", "bit", "", "0", "Reserved for future health faults (reads 0)", "", DI_FAILSAFE - DI_FAULT - len(HealthFault)),
    Field("di", DI_FAILSAFE, "failsafe", "bit", "", "1 = active", "Calls are in fail-safe (outputs.failsafe: constant call or no call) because of " + ", ".join(f.name for f in FAILSAFE_FAULTS)),
    Field("di", DI_FORCED, "forced", "bit", "", "1 = forced", "Channel c call is forced (cabinet test)", "channel", MAX_CHANNELS),
    Field("ir", STATUS + 0, "heartbeat", "uint16", "count", "+1 per second, wraps", "Heartbeat counter, incremented every second by the output server"),
    Field("ir", STATUS + 1, "health", "uint16", "bitfield", "bit k = HealthFault k", "Health fault bitfield (" + ", ".join(f"{int(f)} {f.name}" for f in HealthFault) + ")"),
    Field("ir", STATUS + 2, "firmware", "uint16", "", "major*256 + minor", "Firmware version, major and minor"),
    Field("ir", STATUS + 3, "firmware_patch", "uint16", "", "1", "Firmware version, patch"),
    Field("ir", STATUS + 4, "uptime", "uint32", "s", "1", "Uptime of the service (high word at the lower address)"),
    Field("ir", STATUS + 6, "channels", "uint16", "", "1", "Number of configured detector channels"),
    Field("ir", STATUS + 7, "max_channel", "uint16", "", "1", "Highest configured channel number"),
    Field("ir", STATUS + 8, "lanes", "uint16", "", "1", "Number of configured lanes (period block lane slots in use)"),
    Field("ir", STATUS + 9, "classes", "uint16", "", "1", "Number of length classes"),
    Field("ir", STATUS + 10, "fps", "uint16", "frame/s", "0.1", "Processed frames per second"),
    Field("ir", STATUS + 11, "tracked", "uint16", "vehicles", "1", "Vehicles tracked now"),
    Field("ir", STATUS + 12, "dropped", "uint16", "frames", "1, wraps", "Dropped frames since start"),
    Field("ir", STATUS + 13, "map_version", "uint16", "", "1", f"Register map version ({MAP_VERSION})"),
    Field("ir", STATUS + 14, "wall", "uint32", "s", "1", "Unix time of the snapshot (high word at the lower address)"),
    Field("ir", CH_COUNT, "count", "uint16", "vehicles", "1, wraps mod 65536", "Rolling vehicle count of channel c, never reset (difference modulo 65536)", "channel", MAX_CHANNELS),
    Field("ir", CH_OCC, "occupancy", "uint16", "%", "0.1", f"Occupancy of channel c over the rolling window; 0x{FAULT_FLAG:04X} + fault code (210-217) while in fault", "channel", MAX_CHANNELS),
    Field("ir", CH_SPEED, "last_speed", "uint16", "km/h", "0.1", "Speed of the last vehicle on channel c; 0xFFFF = no data", "channel", MAX_CHANNELS),
    Field("ir", CH_LENGTH, "last_length", "uint16", "m", "0.1", "Length of the last vehicle on channel c; 0xFFFF = no data", "channel", MAX_CHANNELS),
    *[
        Field("ir", CH_CLASS + CLASS_STRIDE * k, f"class{k}_count", "uint16", "vehicles", "1, wraps", f"Rolling count of length class {k} on channel c" + (f" (class {k} = measures.length_class_names[{k}], default {_DEFAULT_CLASSES[k]})" if k < len(_DEFAULT_CLASSES) else " (measures.length_class_names)"), "channel", MAX_CHANNELS)
        for k in range(MAX_CLASSES)
    ],
    Field("ir", PERIOD + 0, "period_seq", "uint16", "", "0-255", "Sequence number of the last complete period, +1 per period (mod 256); read it again after the lane records (a separate request): if it changed, read them again"),
    Field("ir", PERIOD + 1, "period_length", "uint16", "s", "1", "Length of the last complete period; 0 = none yet"),
    Field("ir", PERIOD + 2, "period_start", "uint32", "s", "1", "Unix start time of the last complete period (high word at the lower address)"),
    Field("ir", PERIOD + 4, "period_lanes", "uint16", "", "1", "Lane slots filled in the period block"),
    Field("ir", PERIOD + 5, "period_faults", "uint16", "bitfield", "bit k = HealthFault k", "Health faults seen during the period (all lanes)"),
    Field("ir", LANES + 0, "lane_id", "uint16", "", "1", "Lane id of lane slot i (slots sorted by lane id); 0 = slot unused", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 1, "volume", "uint16", "vehicles", "1", "Volume (count) in the period; 0xFFFF = no data", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 2, "period_occupancy", "uint16", "%", "0.1", f"Occupancy in the period; 0x{FAULT_FLAG:04X} + fault code (210-217) if the detector was in fault; 0xFFFF = no data", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 3, "period_speed", "uint16", "km/h", "0.1", "Space-mean speed (Edie) in the period; 0xFFFF = no data", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 4, "fault_code", "uint16", "", "210-217", "NTCIP-1202-style fault code for the period, 0 = no fault", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 5, "flow", "uint16", "veh/h", "1", "Flow (Edie q); 0xFFFF = no data", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 6, "density", "uint16", "veh/km", "0.1", "Density (Edie k); 0xFFFF = no data", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 7, "time_mean_speed", "uint16", "km/h", "0.1", "Time-mean speed; 0xFFFF = no data", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 8, "speed85", "uint16", "km/h", "0.1", "85th-percentile speed; 0xFFFF = no data", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 9, "headway", "uint16", "s", "0.1", "Mean headway; 0xFFFF = no data", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 10, "partial", "uint16", "", "0/1", "1 = the period was not fully observed", "lane", MAX_LANES, LANE_STRIDE),
    Field("ir", LANES + 11, "quality", "uint16", "bitfield", "bit k = HealthFault k", "Health faults seen in the period for the lane", "lane", MAX_LANES, LANE_STRIDE),
    *[
        Field("ir", LANES + 12 + k, f"period_class{k}", "uint16", "vehicles", "1", f"Count of length class {k} in the period", "lane", MAX_LANES, LANE_STRIDE)
        for k in range(MAX_CLASSES)
    ],
    *[
        Field("ir", LANES + 12 + MAX_CLASSES + k, f"lane_reserved{k}", "uint16", "", "0", "Reserved (reads 0)", "lane", MAX_LANES, LANE_STRIDE)
        for k in range(LANE_STRIDE - 12 - MAX_CLASSES)
    ],
    Field("hr", HR_FORCE, "force_call", "uint16", "s", "1", "Forced call of channel c: write N to force the call for N s (clamped to outputs.force_call_max_s), 0 cancels; reads the remaining seconds of a force written over Modbus (0 once it ends or is cancelled elsewhere). Writes refused with exception 01 ILLEGAL FUNCTION unless outputs.allow_writes; unconfigured channel: exception 02", "channel", MAX_CHANNELS),
]

FIELDS: dict[str, Field] = {f.name: f for f in MAP}


def table_size(table: str) -> int:
    return max(f.end for f in MAP if f.table == table)


def valid_mask(table: str) -> np.ndarray:
    """True at every wire address that belongs to the map (requests touching others get exception 02)."""
    mask = np.zeros(table_size(table), dtype=bool)
    for f in MAP:
        if f.table == table:
            for i in range(f.count):
                mask[f.addr(i) : f.addr(i) + f.width] = True
    return mask


# --- encoding -------------------------------------------------------------------------------


def _u16(value: float | None, scale: float = 1.0) -> int:
    """Scaled measurement; None or non-finite -> NO_DATA; clamped below NO_DATA and the fault range."""
    if value is None or not math.isfinite(value):
        return NO_DATA
    return int(min(max(round(value * scale), 0), FAULT_FLAG - 1))


def _put32(arr: np.ndarray, addr: int, value: int) -> None:
    value = int(value) & 0xFFFFFFFF
    arr[addr] = value >> 16
    arr[addr + 1] = value & 0xFFFF


@dataclass
class RegisterImage:
    """The encoded map: DI bits, IR words (heartbeat at IR 0 is filled by the server)."""

    di: np.ndarray  # bool
    ir: np.ndarray  # uint16
    wall: float = 0.0


@dataclass
class Layout:
    """What the encoding needs from the config."""

    channels: list[int]
    lanes: list[int]
    class_names: list[str]
    pulse_s: dict[int, float] = field(default_factory=dict)  # channels in pulse mode -> pulse length

    @classmethod
    def from_site(cls, site: SiteConfig) -> Layout:
        return cls(
            channels=sorted(lp.channel for lp in site.loops),
            lanes=sorted(lane.id for lane in site.lanes)[:MAX_LANES],
            class_names=list(site.measures.length_class_names)[:MAX_CLASSES],
            pulse_s={lp.channel: lp.pulse_ms / 1000.0 for lp in site.loops if lp.mode == "pulse"},
        )


_IR = {f.name: f.address for f in MAP if f.table == "ir"}  # encoding addresses come from MAP
_LANE = {f.name: f.address - LANES for f in MAP if f.per == "lane"}  # offsets in a lane record
_LANE_NO_DATA = ["volume", "period_occupancy", "period_speed", "flow", "density", "time_mean_speed", "speed85", "headway"]
_DI_SIZE = table_size("di")
_IR_SIZE = table_size("ir")


def encode_snapshot(snapshot: DetectorSnapshot, layout: Layout) -> RegisterImage:
    """Encode a snapshot into the map (calls as given: presence; pulse shaping is PulseShaper's job)."""
    di = np.zeros(_DI_SIZE, dtype=bool)
    ir = np.zeros(_IR_SIZE, dtype=np.uint16)
    faults = int(snapshot.faults) & 0xFFFF
    code = fault_code(faults)
    for f in HealthFault:
        di[DI_FAULT + int(f)] = bool(faults >> int(f) & 1)
    di[DI_FAILSAFE] = any(faults >> int(f) & 1 for f in FAILSAFE_FAULTS)

    major, minor, patch = firmware_version()
    ir[_IR["health"]] = faults
    ir[_IR["firmware"]] = (major & 0xFF) << 8 | (minor & 0xFF)
    ir[_IR["firmware_patch"]] = patch
    _put32(ir, _IR["uptime"], int(max(snapshot.uptime_s, 0)))
    ir[_IR["channels"]] = len(layout.channels)
    ir[_IR["max_channel"]] = max(layout.channels, default=0)
    ir[_IR["lanes"]] = len(layout.lanes)
    ir[_IR["classes"]] = len(layout.class_names)
    ir[_IR["fps"]] = _u16(snapshot.fps, 10)
    ir[_IR["tracked"]] = _u16(snapshot.tracked_vehicles)
    ir[_IR["dropped"]] = snapshot.dropped_frames & 0xFFFF
    ir[_IR["map_version"]] = MAP_VERSION
    _put32(ir, _IR["wall"], int(max(snapshot.wall, 0)))

    ir[CH_SPEED : CH_SPEED + MAX_CHANNELS] = NO_DATA
    ir[CH_LENGTH : CH_LENGTH + MAX_CHANNELS] = NO_DATA
    for ch in snapshot.channels:
        if not 1 <= ch.channel <= MAX_CHANNELS:
            continue
        i = ch.channel - 1
        di[DI_CALL + i] = bool(ch.call)
        di[DI_FORCED + i] = bool(ch.forced)
        ir[CH_COUNT + i] = int(ch.count) & 0xFFFF
        ir[CH_OCC + i] = FAULT_FLAG | code if code else min(_u16(ch.occupancy_pct, 10), 1000)
        ir[CH_SPEED + i] = _u16(ch.last_speed_kmh, 10)
        ir[CH_LENGTH + i] = _u16(ch.last_length_m, 10)
        for k, name in enumerate(layout.class_names):
            ir[CH_CLASS + CLASS_STRIDE * k + i] = int(ch.class_counts.get(name, 0)) & 0xFFFF

    _encode_period(ir, snapshot, layout)
    return RegisterImage(di=di, ir=ir, wall=snapshot.wall)


def _encode_period(ir: np.ndarray, snapshot: DetectorSnapshot, layout: Layout) -> None:
    ir[_IR["period_seq"]] = snapshot.period_seq & 0xFF
    by_lane = {agg.lane: agg for agg in snapshot.last_period}
    slots = ir[LANES : LANES + MAX_LANES * LANE_STRIDE].reshape(MAX_LANES, LANE_STRIDE)  # a view
    slots[:, [_LANE[n] for n in _LANE_NO_DATA]] = NO_DATA
    if not by_lane:
        return
    first = next(iter(by_lane.values()))
    ir[_IR["period_length"]] = _u16(first.period_s)
    _put32(ir, _IR["period_start"], int(first.period_start))
    ir[_IR["period_lanes"]] = len(layout.lanes)
    period_faults = 0
    for slot, lane in enumerate(layout.lanes):
        base = LANES + slot * LANE_STRIDE
        ir[base + _LANE["lane_id"]] = lane
        agg = by_lane.get(lane)
        if agg is None:
            continue
        period_faults |= agg.quality
        code = fault_code(agg.quality)
        ir[base + _LANE["volume"]] = min(_u16(agg.count), NO_DATA - 1)
        ir[base + _LANE["period_occupancy"]] = FAULT_FLAG | code if code else _u16(agg.occupancy_pct, 10)
        ir[base + _LANE["period_speed"]] = _u16(agg.speed_kmh, 10)
        ir[base + _LANE["fault_code"]] = code
        ir[base + _LANE["flow"]] = _u16(agg.flow_vph)
        ir[base + _LANE["density"]] = _u16(agg.density_vpkm, 10)
        ir[base + _LANE["time_mean_speed"]] = _u16(agg.time_mean_speed_kmh, 10)
        ir[base + _LANE["speed85"]] = _u16(agg.speed85_kmh, 10)
        ir[base + _LANE["headway"]] = _u16(agg.headway_s, 10)
        ir[base + _LANE["partial"]] = int(agg.partial)
        ir[base + _LANE["quality"]] = agg.quality & 0xFFFF
        for k, name in enumerate(layout.class_names):
            ir[base + _LANE[f"period_class{k}"]] = int(agg.class_counts.get(name, 0)) & 0xFFFF
    ir[_IR["period_faults"]] = period_faults & 0xFFFF


class PulseShaper:
    """Pulse-mode channels: one pulse of pulse_ms per rising edge of the presence call.

    Forced calls and fail-safe calls (FAILSAFE_FAULTS active) pass through as constant calls, as a
    detector card's pulse output does when its fail-safe or test switch is on."""

    def __init__(self, layout: Layout):
        self.layout = layout
        self.prev = np.zeros(MAX_CHANNELS, dtype=bool)
        self.until = np.zeros(MAX_CHANNELS, dtype=np.float64)  # pulse end, monotonic seconds
        self.pulse_ch = np.array([c - 1 for c in layout.pulse_s], dtype=np.int64)
        self.pulse_len = np.array(list(layout.pulse_s.values()), dtype=np.float64)
        self.passthrough = np.zeros(MAX_CHANNELS, dtype=bool)

    def update(self, image: RegisterImage, now: float) -> None:
        """Record edges of the presence calls in ``image`` at monotonic time ``now``."""
        if not len(self.pulse_ch):
            return
        calls = image.di[DI_CALL + self.pulse_ch]
        rising = calls & ~self.prev[self.pulse_ch]
        self.until[self.pulse_ch[rising]] = now + self.pulse_len[rising]
        self.prev[self.pulse_ch] = calls
        self.passthrough[self.pulse_ch] = image.di[DI_FORCED + self.pulse_ch] | bool(image.di[DI_FAILSAFE])

    def calls(self, image: RegisterImage, now: float) -> np.ndarray:
        """Call bits (DI 0..MAX_CHANNELS-1) as seen at monotonic time ``now``."""
        out = image.di[DI_CALL : DI_CALL + MAX_CHANNELS].copy()
        if len(self.pulse_ch):
            pc = self.pulse_ch
            out[pc] = np.where(self.passthrough[pc], out[pc], now < self.until[pc])
        return out


# --- documentation --------------------------------------------------------------------------


def _range(f: Field, table: str, base: int = 0) -> str:
    lo, hi = base + f.address, base + f.end - 1
    return f"{lo}" if lo == hi else f"{lo}–{hi}"


def _class_index(name: str) -> int | None:
    m = re.fullmatch(r"(?:period_)?class(\d+)(?:_count)?", name)
    return int(m.group(1)) if m else None


def describe(layout: Layout | None = None) -> list[dict]:
    """Rows of the map; with a layout, per-channel/per-lane fields are expanded for that config."""
    rows = []
    for f in MAP:
        if layout is None or not f.per:
            items = [(None, f.address, f.end - 1 if f.count > 1 else f.address + f.width - 1)]
            if f.count > 1 and f.stride > 1:
                items = [(None, f.address, f.addr(f.count - 1))]
        elif f.per == "channel":
            items = [(f"ch {c}", f.addr(c - 1), f.addr(c - 1) + f.width - 1) for c in layout.channels]
        else:
            items = [(f"lane {lane}", f.addr(i), f.addr(i)) for i, lane in enumerate(layout.lanes)]
        k = _class_index(f.name)
        if layout is not None and k is not None and k >= len(layout.class_names):
            continue
        for label, lo, hi in items:
            meaning = f.meaning
            if layout is not None and k is not None:
                meaning = meaning.replace(f"length class {k}", f"length class {k} ({layout.class_names[k]})")
            if label is None and f.per == "channel":
                index = f"channel c at {f.address} + (c−1)"
            elif label is None and f.per == "lane":
                index = f"lane slot i at {f.address} + {f.stride}·i"
            else:
                index = label or ""
            rows.append(
                {
                    "table": f.table,
                    "address": f"{lo}" if lo == hi else f"{lo}–{hi}",
                    "one_based": f"{ONE_BASED[f.table] + lo}" if lo == hi else f"{ONE_BASED[f.table] + lo}–{ONE_BASED[f.table] + hi}",
                    "name": f.name,
                    "index": index,
                    "type": f.type,
                    "unit": f.unit,
                    "scale": f.scale,
                    "meaning": meaning,
                }
            )
    return rows


def markdown(layout: Layout | None = None) -> str:
    """The register map document (docs/registers.md is this with no layout)."""
    out = [
        "# Roadwatch Modbus register map",
        "",
        "Generated from `appliance/registers.py` by `roadwatch registers --markdown`; do not edit by hand.",
        "",
        f"Map version {MAP_VERSION}. Addresses are 0-based as sent on the wire; the 1-based column is the",
        "traditional Modicon numbering (10001+ discrete inputs, 30001+ input registers, 40001+ holding",
        "registers). All registers are unsigned 16 bit; `uint32` values take two registers, **high word",
        "first** (at the lower address). `0xFFFF` (65535) means no data. While the detector is in fault,",
        f"occupancy registers hold `0x{FAULT_FLAG:04X}` + an NTCIP-1202-style fault code (e.g. 0xFFD4 = 65492 = 212).",
        "",
        "Requests that touch an address outside the map get exception 02 ILLEGAL DATA ADDRESS; more than",
        f"{MAX_READ_BITS} bits or {MAX_READ_REGS} registers per read get exception 03 ILLEGAL DATA VALUE; coil functions",
        "(FC 1/5/15) get exception 01 ILLEGAL FUNCTION. Holding-register writes get exception 01 ILLEGAL",
        "FUNCTION unless `outputs.allow_writes = true`. Modbus TCP answers its unit id (and 0/255, the",
        "usual TCP wildcards) and returns exception 0B for other unit ids; Modbus RTU answers only its",
        "unit id and stays silent for every other id on the bus.",
        "",
        "Values change once per processed frame (a call change is readable within a millisecond of the",
        "frame being processed; `roadwatch registers --bench-latency N` measures it); the heartbeat counts",
        "seconds from a timer in the output server. RTU: a silence of 50 ms (or 10 character times at low",
        "baud rates) ends a frame, and an incomplete frame before it is dropped.",
        "",
        "A typical controller poll: FC 2 at 0 (one call bit per channel); FC 4 at "
        f"{CH_COUNT} (rolling counts); FC 4 at {PERIOD} (period header) and at {LANES} ({LANE_STRIDE} registers per lane);",
        "FC 4 at 0 (heartbeat, health) to supervise the detector.",
        "",
        "Fault codes:",
        "",
        "| health fault | code | meaning |",
        "|---|---|---|",
    ]
    for bit, code, text in NTCIP_FAULTS:
        out.append(f"| {bit.name} (bit {int(bit)}) | {code} | {text} |")
    for table in ("di", "ir", "hr"):
        out += ["", f"## {TABLE_NAMES[table]}", "", "| address | 1-based | name | index | type | unit | scale | meaning |", "|---|---|---|---|---|---|---|---|"]
        for r in describe(layout):
            if r["table"] == table:
                out.append(
                    f"| {r['address']} | {r['one_based']} | {r['name']} | {r['index']} | {r['type']} | {r['unit']} | {r['scale']} | {r['meaning']} |"
                )
    return "\n".join(out) + "\n"
