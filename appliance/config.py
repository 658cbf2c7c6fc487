"""The site configuration (one TOML file): schema, defaults, validation with errors naming the key."""

# Lanes, loops and zones may be given in road metres (*_m) or image pixels (*_px); after loading,
# every geometry is also available in metres through the calibration homography.

from __future__ import annotations

import dataclasses
import difflib
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from appliance.geometry import CalibrationError, Homography, polygon_contains

DEFAULT_CONFIG_PATH = "/etc/roadwatch/config.toml"
EMBEDDED_DEMO = Path(__file__).with_name("data") / "demo.toml"


class ConfigError(ValueError):
    """A configuration problem, naming the key (dotted path) and what is wrong."""

    def __init__(self, key: str, problem: str, source: str | None = None):
        self.key, self.problem, self.source = key, problem, source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}{key}: {problem}")


# ---------------------------------------------------------------------------------------------
# Schema. Every section is a dataclass; field defaults are the documented defaults.


@dataclass
class SiteInfo:
    name: str = "unnamed site"
    description: str = ""


@dataclass
class SourceConfig:
    # "synthetic:PRESET[?seed=N]", a video file path, "images:DIR/in%06d.jpg", "rtsp://...",
    # "http://...", or a V4L2 device ("/dev/v4l/by-id/..." or "/dev/videoN").
    url: str = "synthetic:free-flow"
    width: int = 640
    height: int = 480
    fps: float = 25.0
    pixel_format: str = ""  # V4L2 fourcc, e.g. "MJPG"; empty = driver default
    open_timeout_s: float = 10.0
    read_timeout_s: float = 5.0
    reconnect_max_s: float = 30.0
    loop: bool = False  # files: start again at the end (demos)
    realtime: bool = True  # files: pace at the capture rate instead of as fast as possible
    # interlaced camera (analogue through an encoder): each frame's two fields were taken half a frame
    # apart; track on the top field alone, its lines doubled (moving edges would otherwise be combed)
    deinterlace: bool = False


@dataclass
class CalibrationConfig:
    image_px: list[list[float]] = field(default_factory=list)
    road_m: list[list[float]] = field(default_factory=list)
    max_error_m: float = 0.5  # warn/refuse above this mean reprojection error


@dataclass
class LaneConfig:
    id: int = 0
    direction: str = "approaching"  # "approaching" (Y decreasing) or "receding" (Y increasing)
    polygon_m: list[list[float]] | None = None
    polygon_px: list[list[float]] | None = None
    region_y_m: list[float] | None = None  # Edie region [y0, y1]; default: the lane's extent
    count_y_m: float | None = None  # count position; default: middle of the region
    detection_y_m: list[float] | None = None  # where features are detected; default from direction
    exit_y_m: list[float] | None = None  # where vehicles are finalised; default from direction


@dataclass
class LoopConfig:
    id: str = ""
    lane: int = 0
    channel: int = 0  # controller channel, 1-based
    y_m: float | None = None  # along-road start of the loop (smaller Y edge)
    length_m: float = 1.8  # 6 ft, a common loop length
    polygon_m: list[list[float]] | None = None
    polygon_px: list[list[float]] | None = None
    mode: str = "presence"  # "presence" or "pulse"
    pulse_ms: int = 125
    trap_with: str | None = None  # id of the second loop of a speed trap


@dataclass
class TrackingParams:
    """One parameter set for all scenes (the papers insist on it). Distances in metres."""

    max_features: int = 512
    # Frames wider than this are scaled down to it (keeping their aspect) before the vision stages, so the pixel
    # parameters below mean the same on every camera; 0 works on frames at full size. (At full size a 1280x720
    # camera shows each vehicle with four times the corners, parts of it enough for a vehicle of their own.)
    work_width_px: int = 640
    template_px: int = 9
    search_radius_px: int = 6
    # minimum eigenvalue of the normalised structure tensor, in daylight (see appliance.corners.dim_scale)
    corner_min_eig: float = 0.002
    corner_spacing_px: int = 6
    corners_per_frame: int = 48
    ncc_min: float = 0.7
    max_accel_mps2: float = 8.0
    max_lateral_mps: float = 4.0
    max_speed_kmh: float = 200.0
    connection_m: float = 5.0  # r0: features closer than this may be one vehicle
    segmentation_m: float = 2.0  # pair dismissed when its distance range exceeds this
    min_features: int = 4  # a vehicle needs at least this many features
    min_track_frames: int = 5
    stabilise: bool = True
    stabilise_model: str = "translation"  # the only model implemented (image shift from the fiducials)
    connection_lateral_m: float = 2.5  # r0 across the road (features of one vehicle are this close)
    segmentation_lateral_m: float = 1.0  # pair dismissed when its lateral distance range exceeds this
    segmentation_per_m: float = 0.1  # extra along-road allowance per metre travelled (feature heights)
    static_drop_s: float = 1.0  # a feature that has not moved static_min_move_px by then is dropped
    static_min_move_px: float = 4.0
    # hold a loop's call while the image shows a vehicle standing on it (by day: appliance.presence)
    standing_calls: bool = True


@dataclass
class MeasuresConfig:
    period_s: int = 300
    length_class_bounds_m: list[float] = field(default_factory=lambda: [2.1, 6.1, 13.1])
    length_class_names: list[str] = field(
        default_factory=lambda: ["motorcycle", "small", "medium", "large"]
    )
    occupancy_window_s: float = 60.0


@dataclass
class StoreConfig:
    path: str = "roadwatch.sqlite"
    retention_days: float = 400.0
    max_mb: float = 2048.0
    trajectories: bool = False


@dataclass
class ModbusTcpConfig:
    enabled: bool = False
    host: str = "0.0.0.0"
    port: int = 502
    unit_id: int = 1


@dataclass
class ModbusRtuConfig:
    enabled: bool = False
    port: str = "/dev/ttyUSB0"
    baudrate: int = 19200
    parity: str = "E"
    stopbits: int = 1
    bytesize: int = 8
    unit_id: int = 1


@dataclass
class SerialLineConfig:
    enabled: bool = False
    port: str = "/dev/ttyS0"
    baudrate: int = 9600


@dataclass
class OutputsConfig:
    failsafe: str = "call"  # on camera/tracker fault: "call" (constant call) or "no-call"
    allow_writes: bool = False  # holding-register writes (force call) from the controller
    force_call_max_s: float = 300.0
    modbus_tcp: ModbusTcpConfig = field(default_factory=ModbusTcpConfig)
    modbus_rtu: ModbusRtuConfig = field(default_factory=ModbusRtuConfig)
    serial: SerialLineConfig = field(default_factory=SerialLineConfig)


@dataclass
class StatusConfig:
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = 8765
    allow_commands: bool = True  # force-call and reload from the local config tool


@dataclass
class HealthConfig:
    dark_level: float = 12.0  # mean grey below this = too dark
    frozen_s: float = 5.0
    no_hits_s: float = 900.0
    locked_on_s: float = 300.0
    shake_px: float = 25.0
    overload_drop_pct: float = 20.0


@dataclass
class SiteConfig:
    site: SiteInfo = field(default_factory=SiteInfo)
    source: SourceConfig = field(default_factory=SourceConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    lanes: list[LaneConfig] = field(default_factory=list)
    loops: list[LoopConfig] = field(default_factory=list)
    fiducials: list[list[float]] = field(default_factory=list)  # [x, y] image pixels
    tracking: TrackingParams = field(default_factory=TrackingParams)
    measures: MeasuresConfig = field(default_factory=MeasuresConfig)
    store: StoreConfig = field(default_factory=StoreConfig)
    outputs: OutputsConfig = field(default_factory=OutputsConfig)
    status: StatusConfig = field(default_factory=StatusConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    # filled by validation, not read from the file
    homography: Homography | None = field(default=None, repr=False, compare=False)
    path: str | None = field(default=None, repr=False, compare=False)
    raw: dict = field(default_factory=dict, repr=False, compare=False)

    def lane(self, lane_id: int) -> LaneConfig:
        for lane in self.lanes:
            if lane.id == lane_id:
                return lane
        raise KeyError(lane_id)

    def loop_by_channel(self) -> dict[int, LoopConfig]:
        return {lp.channel: lp for lp in self.loops}

    def to_toml(self) -> str:
        """The file form of this configuration (as loaded, with unknown-free keys)."""
        import tomli_w

        return tomli_w.dumps(self.raw if self.raw else to_dict(self))


# ---------------------------------------------------------------------------------------------
# Generic loading of dataclasses from TOML tables.


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp)).replace("typing.", "")


def _convert(value: Any, tp, key: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        errors = []
        for a in args:
            try:
                return _convert(value, a, key)
            except ConfigError as e:
                errors.append(e.problem)
        raise ConfigError(key, errors[0])
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(key, f"expected a table, got {type(value).__name__}")
        return _load_dataclass(tp, value, key)
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(key, f"expected a list, got {type(value).__name__}")
        return [_convert(v, item_tp, f"{key}[{i}]") for i, v in enumerate(value)]
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, f"expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(key, f"expected a number, got {value!r}")
        if not np.isfinite(value):
            raise ConfigError(key, f"expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(key, f"expected a string, got {value!r}")
        return value
    raise ConfigError(key, f"unsupported type {_type_name(tp)}")


def _load_dataclass(cls, table: dict, prefix: str):
    hints = typing.get_type_hints(cls)
    derived = ("homography", "path", "raw") if cls is SiteConfig else ()
    names = [f.name for f in dataclasses.fields(cls) if f.name not in derived]
    kwargs = {}
    for k, v in table.items():
        key = f"{prefix}.{k}" if prefix else k
        if k not in names:
            close = difflib.get_close_matches(k, names, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise ConfigError(key, f"unknown key{hint}")
        kwargs[k] = _convert(v, hints[k], key)
    return cls(**kwargs)


def to_dict(obj: Any) -> dict:
    """Dataclass -> plain dict for TOML (None values dropped, TOML has no null)."""

    def clean(v):
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items() if x is not None}
        if isinstance(v, list):
            return [clean(x) for x in v]
        return v

    d = dataclasses.asdict(obj)
    for k in ("homography", "path", "raw"):
        d.pop(k, None)
    return clean(d)


# ---------------------------------------------------------------------------------------------
# Validation and derived geometry.


def _polygon(points, key: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ConfigError(key, "expected a list of [x, y] pairs")
    if len(arr) < 3:
        raise ConfigError(key, f"a polygon needs at least 3 points, got {len(arr)}")
    area = 0.5 * abs(np.dot(arr[:, 0], np.roll(arr[:, 1], -1)) - np.dot(arr[:, 1], np.roll(arr[:, 0], -1)))
    if area < 1e-6:
        raise ConfigError(key, "polygon has no area")
    return arr


def clip_polygon_y(poly: np.ndarray, y0: float, y1: float) -> np.ndarray:
    """Part of a polygon between two along-road positions (Sutherland-Hodgman on two half-planes)."""

    def clip(pts, inside, cross):
        out = []
        n = len(pts)
        for i in range(n):
            a, b = pts[i], pts[(i + 1) % n]
            ia, ib = inside(a), inside(b)
            if ia:
                out.append(a)
            if ia != ib:
                out.append(cross(a, b))
        return out

    def crossing(y):
        def f(a, b):
            s = (y - a[1]) / (b[1] - a[1])
            return np.array([a[0] + s * (b[0] - a[0]), y])

        return f

    pts = list(np.asarray(poly, dtype=np.float64))
    pts = clip(pts, lambda p: p[1] >= y0, crossing(y0))
    if pts:
        pts = clip(pts, lambda p: p[1] <= y1, crossing(y1))
    return np.array(pts, dtype=np.float64).reshape(-1, 2)


def _check_inside_image(poly_px: np.ndarray, key: str, width: int, height: int) -> None:
    margin = 1.0
    if (
        poly_px[:, 0].min() < -margin
        or poly_px[:, 1].min() < -margin
        or poly_px[:, 0].max() > width - 1 + margin
        or poly_px[:, 1].max() > height - 1 + margin
    ):
        raise ConfigError(
            key,
            f"falls outside the {width}x{height} image "
            f"(x {poly_px[:, 0].min():.0f}..{poly_px[:, 0].max():.0f}, "
            f"y {poly_px[:, 1].min():.0f}..{poly_px[:, 1].max():.0f})",
        )


def _validate(cfg: SiteConfig) -> None:
    src = cfg.source
    if src.width <= 0 or src.height <= 0:
        raise ConfigError("source.width", "width and height must be positive")
    if src.fps <= 0 or src.fps > 240:
        raise ConfigError("source.fps", f"must be in (0, 240], got {src.fps}")

    cal = cfg.calibration
    if not cal.image_px or not cal.road_m:
        raise ConfigError("calibration", "needs image_px and road_m point lists (at least 4 pairs)")
    try:
        H = Homography.from_points(cal.image_px, cal.road_m)
    except CalibrationError as e:
        raise ConfigError("calibration", str(e).removeprefix("calibration: ")) from None
    err = H.reprojection_error_m(cal.image_px, cal.road_m)
    if float(err.mean()) > cal.max_error_m:
        raise ConfigError(
            "calibration",
            f"mean reprojection error {err.mean():.2f} m exceeds calibration.max_error_m = {cal.max_error_m}",
        )
    cfg.homography = H

    if not cfg.lanes:
        raise ConfigError("lanes", "at least one lane is needed")
    seen: set[int] = set()
    for i, lane in enumerate(cfg.lanes):
        key = f"lanes[{i}]"
        if lane.id <= 0:
            raise ConfigError(f"{key}.id", "lane ids are positive integers")
        if lane.id in seen:
            raise ConfigError(f"{key}.id", f"duplicate lane id {lane.id}")
        seen.add(lane.id)
        if lane.direction not in ("approaching", "receding"):
            raise ConfigError(f"{key}.direction", f"must be 'approaching' or 'receding', got {lane.direction!r}")
        if (lane.polygon_m is None) == (lane.polygon_px is None):
            raise ConfigError(key, "give exactly one of polygon_m or polygon_px")
        if lane.polygon_px is not None:
            px = _polygon(lane.polygon_px, f"{key}.polygon_px")
            lane.polygon_m = H.img_to_road(px).tolist()
        else:
            px = H.road_to_img(_polygon(lane.polygon_m, f"{key}.polygon_m"))
        _check_inside_image(px, key, src.width, src.height)
        poly = np.asarray(lane.polygon_m)
        ylo, yhi = float(poly[:, 1].min()), float(poly[:, 1].max())
        if lane.region_y_m is None:
            lane.region_y_m = [ylo, yhi]
        for name in ("region_y_m", "detection_y_m", "exit_y_m"):
            rng = getattr(lane, name)
            if rng is None:
                continue
            if len(rng) != 2 or rng[0] >= rng[1]:
                raise ConfigError(f"{key}.{name}", f"expected [y0, y1] with y0 < y1, got {rng}")
            if rng[0] < ylo - 0.5 or rng[1] > yhi + 0.5:
                raise ConfigError(f"{key}.{name}", f"{rng} is outside the lane's extent [{ylo:.1f}, {yhi:.1f}] m")
        if lane.count_y_m is None:
            lane.count_y_m = 0.5 * (lane.region_y_m[0] + lane.region_y_m[1])
        elif not lane.region_y_m[0] <= lane.count_y_m <= lane.region_y_m[1]:
            raise ConfigError(f"{key}.count_y_m", f"{lane.count_y_m} is outside the lane region {lane.region_y_m}")

    loop_ids: set[str] = set()
    channels: set[int] = set()
    for i, lp in enumerate(cfg.loops):
        key = f"loops[{i}]"
        if not lp.id:
            raise ConfigError(f"{key}.id", "every loop needs an id")
        if lp.id in loop_ids:
            raise ConfigError(f"{key}.id", f"duplicate loop id {lp.id!r}")
        loop_ids.add(lp.id)
        if lp.lane not in seen:
            raise ConfigError(f"{key}.lane", f"no lane with id {lp.lane}")
        if lp.channel < 1 or lp.channel > 256:
            raise ConfigError(f"{key}.channel", f"channels are 1..256, got {lp.channel}")
        if lp.channel in channels:
            raise ConfigError(f"{key}.channel", f"channel {lp.channel} is assigned to two loops")
        channels.add(lp.channel)
        if lp.mode not in ("presence", "pulse"):
            raise ConfigError(f"{key}.mode", f"must be 'presence' or 'pulse', got {lp.mode!r}")
        if lp.length_m <= 0:
            raise ConfigError(f"{key}.length_m", "must be positive")
        given = [lp.y_m is not None, lp.polygon_m is not None, lp.polygon_px is not None]
        if sum(given) != 1:
            raise ConfigError(key, "give exactly one of y_m (with length_m), polygon_m or polygon_px")
        lane_poly = np.asarray(cfg.lane(lp.lane).polygon_m)
        if lp.y_m is not None:
            poly = clip_polygon_y(lane_poly, lp.y_m, lp.y_m + lp.length_m)
            if len(poly) < 3:
                raise ConfigError(f"{key}.y_m", f"loop at {lp.y_m} m is outside lane {lp.lane}")
            lp.polygon_m = poly.tolist()
        elif lp.polygon_px is not None:
            lp.polygon_m = H.img_to_road(_polygon(lp.polygon_px, f"{key}.polygon_px")).tolist()
        poly = _polygon(lp.polygon_m, f"{key}.polygon_m")
        centre = poly.mean(axis=0, keepdims=True)
        if not polygon_contains(lane_poly, centre)[0]:
            raise ConfigError(key, f"loop is not inside lane {lp.lane}")
        _check_inside_image(H.road_to_img(poly), key, src.width, src.height)
        if lp.y_m is None:
            lp.y_m = float(poly[:, 1].min())
            lp.length_m = float(poly[:, 1].max() - poly[:, 1].min())
    for i, lp in enumerate(cfg.loops):
        if lp.trap_with is not None and lp.trap_with not in loop_ids:
            raise ConfigError(f"loops[{i}].trap_with", f"no loop with id {lp.trap_with!r}")

    for i, f in enumerate(cfg.fiducials):
        if len(f) != 2 or not (0 <= f[0] < src.width and 0 <= f[1] < src.height):
            raise ConfigError(f"fiducials[{i}]", f"{f} is not a point inside the {src.width}x{src.height} image")

    t = cfg.tracking
    if t.work_width_px != 0 and t.work_width_px < 160:
        raise ConfigError("tracking.work_width_px", f"must be 0 (full size) or at least 160, got {t.work_width_px}")
    if t.template_px % 2 == 0 or t.template_px < 5:
        raise ConfigError("tracking.template_px", "must be odd and at least 5")
    if t.connection_m <= t.segmentation_m:
        raise ConfigError("tracking.connection_m", "must be larger than tracking.segmentation_m")
    if t.stabilise_model != "translation":
        raise ConfigError("tracking.stabilise_model",
                          f"{t.stabilise_model!r}: only 'translation' is implemented (the stabiliser estimates an image shift)")

    m = cfg.measures
    if m.period_s <= 0 or 86400 % m.period_s != 0:
        raise ConfigError("measures.period_s", f"must divide a day evenly (e.g. 60, 300, 900), got {m.period_s}")
    if len(m.length_class_names) != len(m.length_class_bounds_m) + 1:
        raise ConfigError("measures.length_class_names", "needs one more name than length_class_bounds_m")
    if list(m.length_class_bounds_m) != sorted(m.length_class_bounds_m):
        raise ConfigError("measures.length_class_bounds_m", "must be increasing")

    o = cfg.outputs
    if o.failsafe not in ("call", "no-call"):
        raise ConfigError("outputs.failsafe", f"must be 'call' or 'no-call', got {o.failsafe!r}")
    for name, unit in (("modbus_tcp", o.modbus_tcp.unit_id), ("modbus_rtu", o.modbus_rtu.unit_id)):
        if not 1 <= unit <= 247:
            raise ConfigError(f"outputs.{name}.unit_id", f"must be 1..247, got {unit}")
    if not 0 < o.modbus_tcp.port < 65536:
        raise ConfigError("outputs.modbus_tcp.port", f"not a TCP port: {o.modbus_tcp.port}")
    if o.modbus_rtu.parity not in ("N", "E", "O"):
        raise ConfigError("outputs.modbus_rtu.parity", "must be 'N', 'E' or 'O'")
    if o.modbus_rtu.stopbits not in (1, 2):
        raise ConfigError("outputs.modbus_rtu.stopbits", "must be 1 or 2")
    if cfg.store.retention_days <= 0 or cfg.store.max_mb <= 0:
        raise ConfigError("store", "retention_days and max_mb must be positive")


def parse_site(data: dict, source: str | None = None) -> SiteConfig:
    """Build and validate a SiteConfig from a parsed TOML dict. Raises ConfigError."""
    try:
        cfg = _load_dataclass(SiteConfig, data, "")
        _validate(cfg)
    except ConfigError as e:
        raise ConfigError(e.key, e.problem, source) from None
    cfg.raw = data
    cfg.path = source
    return cfg


def working_size(site: SiteConfig) -> tuple[int, int]:
    """The frame size the vision stages work at (see TrackingParams.work_width_px)."""
    w, h, ww = int(site.source.width), int(site.source.height), int(site.tracking.work_width_px)
    if ww <= 0 or w <= ww:
        return w, h
    return ww, max(1, round(h * ww / w))


def at_working_size(site: SiteConfig) -> SiteConfig:
    """A validated site with its image geometry (source size, calibration points, fiducials, homography) in the
    pixels of its working size; the site itself when that is its full size."""
    (ww, wh), (w, h) = working_size(site), (int(site.source.width), int(site.source.height))
    if (ww, wh) == (w, h):
        return site
    sx, sy = ww / w, wh / h
    out = dataclasses.replace(
        site, source=dataclasses.replace(site.source, width=ww, height=wh),
        calibration=dataclasses.replace(site.calibration, image_px=[[x * sx, y * sy] for x, y in site.calibration.image_px]),
        fiducials=[[x * sx, y * sy] for x, y in site.fiducials])
    out.homography = Homography.from_matrix(site.homography.H @ np.diag([1.0 / sx, 1.0 / sy, 1.0]))
    return out


def load_site(path: str | Path) -> SiteConfig:
    """Read and validate a site config file. Raises ConfigError naming the key and the problem."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("file", "does not exist", str(p)) from None
    except OSError as e:
        raise ConfigError("file", f"cannot be read ({e.strerror})", str(p)) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError("file", f"is not valid TOML ({e})", str(p)) from None
    return parse_site(data, str(p))


def load_demo() -> SiteConfig:
    """The embedded default site: the demo scene on the synthetic live source."""
    return load_site(EMBEDDED_DEMO)
