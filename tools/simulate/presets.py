"""Scenario presets: road, traffic demand, camera and conditions for each named scene."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field


MIN_CURVE_RADIUS_M = 200.0  # tighter bends leave the view before the count region (and are not 'gentle')


@dataclass
class SceneParams:
    """Everything that defines a scene; a preset is a set of overrides of these defaults."""

    # road
    lanes_approaching: int = 2
    lanes_receding: int = 0
    lane_width_m: float = 3.5
    curve_radius_m: float = 0.0  # 0 = straight; + bends right, - left; |R| >= MIN_CURVE_RADIUS_M (gentle)
    # traffic (per lane)
    demand_vph: float = 900.0
    demand_profile: list[list[float]] = field(default_factory=list)  # [[t_s, factor], ...] piecewise linear
    lane_demand_factors: list[float] = field(default_factory=list)  # per lane (left to right); default all 1
    speed_limit_kmh: float = 100.0
    class_mix: dict[str, float] = field(
        default_factory=lambda: {"motorcycle": 0.02, "car": 0.78, "van": 0.1, "truck": 0.05, "artic": 0.03, "bus": 0.02}
    )
    idm_headway_s: float = 1.4
    lane_changes: bool = True
    # a signal downstream of the approaching lanes: [stop_line_y_m, cycle_s, red_s] (None = none)
    signal: list[float] | None = None
    # camera
    cam_height_m: float = 10.0
    cam_tilt_deg: float = 16.0
    cam_pan_deg: float | None = None  # None = aim at the road centre 60 m away
    cam_offset_m: float = 2.0  # lateral distance of the pole from the right road edge (negative = over the road)
    focal_scale: float = 1.1  # focal length / image width
    # conditions
    sun_elevation_deg: float = 40.0
    sun_azimuth_deg: float = 120.0  # direction the sun shines FROM, degrees clockwise from +Y
    shadows: bool = True
    overcast: bool = False
    dusk: bool = False
    night: bool = False
    rain: bool = False
    day_to_night: list[float] | None = None  # [t_start, t_end] s: light fades from day to night in between
    shake_px: float = 0.0  # wind-shake standard deviation
    drift_px_per_min: float = 0.0
    motion_blur: bool = True
    defocus: float = 0.6  # Gaussian sigma (px): slight lens softness; real cameras are never pixel-sharp
    noise_sigma: float = 2.5
    auto_gain: bool = True
    jpeg_quality: int = 0  # >0: JPEG-compress every frame at this quality (stream only; video is mp4 anyway)
    video_crf: int = 23
    # stream defects
    repeat_frames: int = 1  # each rendered frame written this many times (15 fps padded to 30 fps = 2)
    drop_prob: float = 0.0
    jitter_ms: float = 0.0
    interlaced: bool = False  # each frame's odd lines (its bottom field) taken half a frame after its even lines


PRESETS: dict[str, str] = {
    "free-flow": "2 approaching lanes, moderate demand, sunny, everyone at the speed limit.",
    "demo": "The embedded demo site: 3 lanes (2 approaching, 1 receding), mixed traffic, sun with shadows.",
    "dense": "4 approaching lanes near capacity (1800 veh/h/lane), short headways, lane changes.",
    "shockwave": "3 lanes near capacity behind a signal just out of view: stop waves run up through the view and clear.",
    "stopped-queue": "2 lanes with a red light in view: a standing queue over the loops, then discharge.",
    "long-shadows": "Low sun from the side: long vehicle shadows reaching into the neighbouring lanes.",
    "night": "Dark road lit only under lamps, headlights with glare, tail lights, high sensor noise.",
    "rain": "Rain streaks, low contrast, dark wet road with dimmer markings, slight defocus, overcast light.",
    "wind-shake": "Camera pole in wind: jitter of a few px plus a slow drift of about 20 px per minute.",
    "trucks-and-buses": "Heavy-vehicle mix (trucks, articulated trucks, buses) that occlude the lanes behind.",
    "two-directions": "2 approaching + 2 receding lanes, camera on a pole at the roadside.",
    "dusk": "Low light after sunset, headlights on, gain riding high.",
    "day-to-night": "3 lanes from sunny day to lamp-lit night over the first 4 minutes: gain, shadows, headlights.",
    "curve": "3 lanes (2 approaching, 1 receding) on a gentle left-hand curve of 350 m radius, sun with shadows.",
    "defects": "free-flow footage at 15 fps padded to 30 fps, dropped frames and timestamp jitter.",
}

_OVERRIDES: dict[str, dict] = {
    "free-flow": dict(demand_vph=700.0),
    "demo": dict(lanes_approaching=2, lanes_receding=1, demand_vph=800.0, speed_limit_kmh=90.0),
    "dense": dict(
        lanes_approaching=4, demand_vph=1800.0, idm_headway_s=1.1, speed_limit_kmh=90.0, cam_height_m=12.0,
    ),
    "shockwave": dict(
        lanes_approaching=3, demand_vph=1000.0, speed_limit_kmh=80.0, signal=[-10.0, 80.0, 28.0],
        idm_headway_s=1.2,
    ),
    "stopped-queue": dict(
        lanes_approaching=2, demand_vph=900.0, speed_limit_kmh=60.0, signal=[18.0, 120.0, 80.0],
    ),
    "long-shadows": dict(lanes_approaching=3, sun_elevation_deg=12.0, sun_azimuth_deg=260.0, demand_vph=1000.0),
    "night": dict(night=True, shadows=False, noise_sigma=6.0, lanes_approaching=2, lanes_receding=1),
    "rain": dict(rain=True, overcast=True, shadows=False, noise_sigma=4.0, defocus=1.0),
    "wind-shake": dict(shake_px=2.5, drift_px_per_min=20.0, lanes_approaching=3),
    "trucks-and-buses": dict(
        lanes_approaching=3,
        demand_vph=1000.0,
        class_mix={"motorcycle": 0.02, "car": 0.46, "van": 0.12, "truck": 0.16, "artic": 0.14, "bus": 0.10},
        speed_limit_kmh=85.0,
    ),
    "two-directions": dict(lanes_approaching=2, lanes_receding=2, demand_vph=800.0, cam_offset_m=3.0),
    "dusk": dict(dusk=True, shadows=False, noise_sigma=4.5, lanes_receding=1),
    "day-to-night": dict(lanes_approaching=2, lanes_receding=1, day_to_night=[20.0, 240.0], noise_sigma=4.0),
    "curve": dict(lanes_approaching=2, lanes_receding=1, curve_radius_m=-350.0, demand_vph=800.0,
                  speed_limit_kmh=80.0),
    "defects": dict(repeat_frames=2, drop_prob=0.01, jitter_ms=4.0),
}


def scene_params(preset: str, **overrides: object) -> SceneParams:
    """The parameters of a preset with keyword overrides applied; unknown names raise ValueError."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of: {', '.join(PRESETS)}")
    names = {f.name for f in dataclasses.fields(SceneParams)}
    p = SceneParams(**_OVERRIDES.get(preset, {}))
    for k, v in overrides.items():
        if k not in names:
            raise ValueError(f"unknown scene parameter {k!r}")
        if v is not None:
            setattr(p, k, v)
    if not 1 <= p.lanes_approaching + p.lanes_receding <= 6:
        raise ValueError("a scene needs 1 to 6 lanes in total")
    if p.curve_radius_m != 0 and abs(p.curve_radius_m) < MIN_CURVE_RADIUS_M:
        raise ValueError(f"curve radius {p.curve_radius_m} m is too tight: use 0 (straight) or |R| >= "
                         f"{MIN_CURVE_RADIUS_M:g} m")
    if p.repeat_frames < 1:
        raise ValueError("repeat_frames must be >= 1")
    return p
