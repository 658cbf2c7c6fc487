"""Health supervision: each named fault is raised with its time after its condition held, and
cleared; transitions are reported once; the snapshot applies fail-safe and force-calls."""

from __future__ import annotations

import numpy as np

from appliance.config import HealthConfig
from appliance.health import DARK_HOLD_S, HealthMonitor
from appliance.types import ChannelState, HealthFault, LoopEvent

T0 = 1767225600.0


def _img(level: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(rng.normal(level, 10, (120, 160)), 0, 255).astype(np.uint8)


def _ch(call: bool, forced: bool = False) -> ChannelState:
    return ChannelState(channel=1, loop_id="L1", lane=1, call=call, count=0, occupancy_pct=0.0,
                        last_speed_kmh=None, last_length_m=None, forced=forced)


def test_frozen_image_and_darkness() -> None:
    h = HealthMonitor(HealthConfig(frozen_s=2.0, dark_level=12.0))
    same = _img(100)
    for i in range(60):  # 25 fps, identical frames for 2.4 s
        h.observe_frame(i / 25, T0 + i / 25, same)
    assert h.active(HealthFault.FROZEN_IMAGE)
    tr = h.transitions()
    assert [(t.fault, t.active) for t in tr] == [(HealthFault.FROZEN_IMAGE, True)]
    assert tr[0].wall == T0 + 50 / 25  # raised when it had held for frozen_s
    h.observe_frame(2.5, T0 + 2.5, _img(100, seed=1))
    assert not h.active(HealthFault.FROZEN_IMAGE)
    assert h.transitions()[0].active is False
    t = 3.0
    while t < 3.0 + DARK_HOLD_S + 0.2:
        h.observe_frame(t, T0 + t, _img(5, seed=int(t * 25)))
        t += 0.04
    assert h.active(HealthFault.TOO_DARK) and h.bits & (1 << HealthFault.TOO_DARK)
    assert h.names() == ["TOO_DARK"]


def test_locked_on_no_hits_overload_and_tracker_faults() -> None:
    h = HealthMonitor(HealthConfig(locked_on_s=10.0, no_hits_s=20.0, overload_drop_pct=20.0, shake_px=5.0))
    for k in range(0, 120):  # 12 s with the call held on
        h.observe_channels(k / 10, T0 + k / 10, [_ch(True)], [])
    assert h.active(HealthFault.LOCKED_ON) and not h.active(HealthFault.NO_HITS)
    h.observe_channels(12.0, T0 + 12, [_ch(True, forced=True)], [])  # a forced call is not a fault
    assert not h.active(HealthFault.LOCKED_ON)
    h.observe_channels(21.0, T0 + 21, [_ch(False)], [])
    assert h.active(HealthFault.NO_HITS)
    ev = LoopEvent("L1", 1, 1, 21.5, 21.7, T0 + 21.5, T0 + 21.7, 50.0, 4.0)
    h.observe_channels(22.0, T0 + 22, [_ch(False)], [ev])
    assert not h.active(HealthFault.NO_HITS)
    h.observe_load(30.0, T0 + 30, frames=70, dropped=30)
    assert h.active(HealthFault.OVERLOAD)
    h.observe_load(40.0, T0 + 40, frames=95, dropped=5)
    assert not h.active(HealthFault.OVERLOAD)
    for k in range(60):  # 6 s: longer than both hold times
        h.observe_tracker(50 + k / 10, T0 + 50 + k / 10, {"shake_px": (6.0, 3.0), "fiducials_ok": 1, "fiducials_total": 4})
    assert h.active(HealthFault.HEAVY_SHAKE) and h.active(HealthFault.FIDUCIALS_LOST)
    h.observe_tracker(60.0, T0 + 60, {"shake_px": (0.5, 0.2), "fiducials_ok": 4, "fiducials_total": 4})
    assert not h.active(HealthFault.HEAVY_SHAKE) and not h.active(HealthFault.FIDUCIALS_LOST)


def test_snapshot_applies_failsafe_and_force_calls(tmp_path, shared_data) -> None:
    from appliance.config import load_site
    from appliance.service import Service, ServiceHooks
    from test_service_sitefiles import cdnet_site

    site = load_site(cdnet_site(tmp_path, shared_data, frames=1, outputs={"failsafe": "no-call", "force_call_max_s": 60.0}))
    svc = Service(site, ServiceHooks(make_source=lambda s: None))
    chans = [ChannelState(c, f"L{c}", c, True, 3, 10.0, 50.0, 4.0) for c in (1, 2)]
    snap = svc.build_snapshot(T0, chans)
    assert [c.call for c in snap.channels] == [True, True] and snap.faults == 0
    svc.health.set(HealthFault.CAMERA_LOST, True, 0.0, T0)
    svc.force_call(2, 1e6)  # clamped to force_call_max_s
    snap = svc.build_snapshot(T0, chans)
    assert [c.call for c in snap.channels] == [False, True]  # fail-safe no-call; the forced one stays on
    assert snap.channels[1].forced and snap.has_fault(HealthFault.CAMERA_LOST)
    assert 59.0 < svc._forced[2] - __import__("time").monotonic() <= 60.0
    svc.force_call(2, 0)
    assert [c.call for c in svc.build_snapshot(T0, chans).channels] == [False, False]
    import pytest

    with pytest.raises(ValueError, match="no detector channel 7"):
        svc.force_call(7, 5)


def test_frames_of_the_wrong_size_raise_config_fault_not_a_crash(tmp_path, shared_data) -> None:
    import cv2

    from appliance.config import load_site
    from appliance.service import Service
    from appliance.store import Store
    from test_service_sitefiles import cdnet_site
    from tools.service_cmd import make_hooks

    w = cv2.VideoWriter(str(tmp_path / "small.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (160, 120))
    for i in range(20):
        w.write(np.full((120, 160, 3), 40 + i, np.uint8))
    w.release()
    site = load_site(cdnet_site(tmp_path, shared_data, frames=1, url="small.avi"))  # the site says 320x240
    svc = Service(site, make_hooks(site))
    svc.run()
    assert svc.frames == 20 and "CONFIG" in svc.health.names()
    events = Store(tmp_path / "store.sqlite", readonly=True).health_events()
    assert events[0]["fault"] == "CONFIG" and "320x240" in events[0]["detail"]
