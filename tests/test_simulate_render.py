"""Simulator rendering: projected boxes match rendered pixels, seeds reproduce, conditions move the image."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from simulate_helpers import CLEAN, changed_pixels_match_box
from tools.simulate.scene import Scene


@pytest.mark.parametrize("cls, y_front", [("car", 40.0), ("truck", 30.0), ("bus", 60.0)])
def test_projected_box_matches_rendered_pixels(cls: str, y_front: float) -> None:
    sc = Scene("free-flow", 4, lane_changes=False, class_mix={cls: 1.0}, **CLEAN)
    empty, rows = sc.render()
    assert rows == []
    tr = sc.traffic
    assert tr._spawn(0)  # lane 1, approaching
    tr.s[0] = tr.layout.lanes[0].s_of(y_front)
    img, rows = sc.render()
    assert len(rows) == 1
    r = rows[0]
    changed_pixels_match_box(img, empty, r)
    assert r["visible_frac"] > 0.85  # half-resolution estimate; a lamp post may cover a sliver
    assert r["y_front_m"] == pytest.approx(y_front)
    assert r["y_rear_m"] == pytest.approx(y_front + r["length_m"])


def test_same_seed_same_frames_different_seed_differs() -> None:
    def frames(seed: int) -> list[np.ndarray]:
        sc = Scene("dense", seed)
        out = []
        for _ in range(15):
            sc.step(0.04)
            out.append(sc.render()[0])
        return out

    a, b, c = frames(11), frames(11), frames(12)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[-1], c[-1])


def test_occluded_vehicle_has_lower_visible_fraction() -> None:
    sc = Scene("free-flow", 4, lane_changes=False, class_mix={"car": 1.0}, **CLEAN)
    tr = sc.traffic
    assert tr._spawn(1)
    tr.s[0] = tr.layout.lanes[1].s_of(60.0)
    _, rows = sc.render()
    alone = rows[0]["visible_frac"]
    # a bus right in front (nearer the camera) in the same lane hides most of the car
    sc2 = Scene("free-flow", 4, lane_changes=False, class_mix={"car": 1.0}, **CLEAN)
    tr2 = sc2.traffic
    assert tr2._spawn(1)
    tr2.s[0] = tr2.layout.lanes[1].s_of(60.0)
    tr2.class_p[:] = 1.0
    tr2.classes = ["bus"]
    assert tr2._spawn(1) or True
    tr2.s[-1] = tr2.layout.lanes[1].s_of(45.0)
    _, rows2 = sc2.render()
    car = next(r for r in rows2 if r["class"] == "car")
    assert alone > 0.9 and car["visible_frac"] < alone - 0.3, (alone, car["visible_frac"])


def test_wind_drift_reaches_15px_per_minute() -> None:
    sc = Scene("wind-shake", 1)
    drift = np.array(sc.conditions.drift(60.0)) - np.array(sc.conditions.drift(0.0))
    shake = np.array([sc.conditions.offset(0.0) for _ in range(300)])
    assert np.linalg.norm(drift) >= 15.0
    assert 1.0 < shake.std(axis=0).max() < 10.0  # a few pixels of jitter
    # and the rendered image really moves: a static patch (the sign) shifts between two frames
    a, _ = sc.render(want_truth=False)
    sc.traffic.t = 60.0
    b, _ = sc.render(want_truth=False)
    o = next(o for o in sc.objects if o.name == "sign")
    y0, x0 = o.y0 + 5, o.x0 + 5
    tpl = a[y0 : y0 + 30, x0 : x0 + 40]
    res = cv2.matchTemplate(b, tpl, cv2.TM_CCOEFF_NORMED)
    _, _, _, (mx, my) = cv2.minMaxLoc(res)
    assert np.hypot(mx - x0, my - y0) >= 8.0  # 20 px of drift minus a few px of shake either way


def test_shake_blur_leaves_the_image_where_it_is() -> None:
    """The wind-shake preset's motion blur must not move the image: the truth's positions come from the
    camera model, so a shift (an even-sized box filter moves it half a pixel) would read as a calibration
    error of about 0.6 m at 90 m in every wind-shake scene."""
    sc = Scene("wind-shake", 1)
    sc.conditions.p = replace(sc.conditions.p, noise_sigma=0.0, defocus=0.0, auto_gain=False, jpeg_quality=0)
    img = np.zeros((480, 640), np.uint8)
    img[201, 301] = 200
    out = sc.conditions.apply(img, 0.0, (0.0, 0.0)).astype(np.float64)
    assert out.max() < 160  # it is blurred ...
    ys, xs = np.mgrid[: out.shape[0], : out.shape[1]]
    centre = np.array([(out * ys).sum(), (out * xs).sum()]) / out.sum()
    assert np.abs(centre - (201.0, 301.0)).max() < 0.05, centre  # ... where it was


@pytest.mark.parametrize("preset", ["night", "rain", "long-shadows", "trucks-and-buses", "stopped-queue"])
def test_condition_presets_render(preset: str) -> None:
    sc = Scene(preset, 1)
    for _ in range(3):
        sc.step(0.04)
    img, rows = sc.render()
    assert img.shape == (480, 640) and img.dtype == np.uint8
    assert rows
    mean = float(img[200:].mean())
    if preset == "night":
        assert mean < 60  # dark scene
    else:
        assert 40 < mean < 200


def test_day_to_night_darkens_and_switches_lights_on() -> None:
    sc = Scene("day-to-night", 1, day_to_night=[0.0, 2.0], auto_gain=False, noise_sigma=0.0)
    day, _ = sc.render(want_truth=False)
    assert not sc.night_lights
    for _ in range(75):
        sc.step(0.04)
    night, _ = sc.render(want_truth=False)
    assert sc.night_lights
    assert night.mean() < 0.4 * day.mean()  # night exposure is 0.28 of day; lamps and headlights add a little
    assert night.max() >= 200  # lit headlights and lamp heads stay bright
