"""Corner detection in dim light: the threshold follows the frame's light down to the sensor's noise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.config import TrackingParams, parse_site
from appliance.corners import DAY_GREY, MIN_DIM_SCALE, CornerDetector, dim_scale
from appliance.pipeline import NIGHT_GREY, VisionPipeline
from appliance.types import Frame
from tests.test_vision_pipeline import H, W, site_dict

NO_FEATURES = np.zeros((0, 2))


def _detector(h: int = 120, w: int = 160) -> CornerDetector:
    """A detector over the whole image that returns every corner it finds (no per-frame cap)."""
    return CornerDetector(TrackingParams(corners_per_frame=1000), (0, 0, w, h), np.full((h, w), 255, np.uint8))


def _texture(seed: int, h: int = 120, w: int = 160) -> np.ndarray:
    """A vehicle-like texture of unit grey-level std."""
    small = np.random.default_rng(seed).normal(0.0, 1.0, (h // 6, w // 6))
    t = cv2.GaussianBlur(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), (3, 3), 0)
    return t / t.std()


@pytest.mark.parametrize("seed", [3, 4, 5, 6])
def test_at_dusk_a_texture_keeps_the_corners_a_daylight_threshold_loses(seed):
    """The same texture (std 30 grey levels by day, mean 110) in half the light (mean 55, std 15): its
    structure tensor falls to a quarter, and a daylight threshold keeps under a tenth of the day's corners
    (2-6 of 82-102 for these textures). The threshold at its floor (half) keeps those that score at least twice
    the daylight threshold by day: a fifth to a half of them (28-39), never all."""
    tex = _texture(seed)
    det = _detector()
    day = np.clip(110 + 30 * tex, 0, 255).astype(np.uint8)
    dusk = np.clip(55 + 15 * tex, 0, 255).astype(np.uint8)
    n_day = len(det.detect(day, None, NO_FEATURES))
    n_fixed = len(det.detect(dusk, None, NO_FEATURES))
    det.scale = dim_scale(float(dusk.mean()))
    assert det.scale == MIN_DIM_SCALE
    n_dim = len(det.detect(dusk, None, NO_FEATURES))
    assert n_day >= 50 and n_fixed <= n_day // 10, (n_day, n_fixed)
    assert n_day // 5 <= n_dim <= n_day // 2 and n_dim >= 4 * n_fixed, (n_day, n_fixed, n_dim)


@pytest.mark.parametrize("sigma", [2.0, 3.0, 4.0, 5.0])
def test_the_lowest_threshold_finds_no_corners_in_a_dim_frames_noise(sigma):
    """A plain road at dusk under a camera's gain noise of std 2-5 grey levels: no corners at the lowest
    threshold (the noise's strongest score is 0.1-0.6 of it; noise of std 6 or more would reach it)."""
    det = _detector()
    det.scale = MIN_DIM_SCALE
    noise = np.clip(55 + np.random.default_rng(int(sigma)).normal(0.0, sigma, (120, 160)), 0, 255).astype(np.uint8)
    assert len(det.detect(noise, None, NO_FEATURES)) == 0


def test_the_threshold_scale_is_one_by_day_and_at_night_and_falls_with_the_light_in_between():
    assert dim_scale(DAY_GREY) == 1.0 and dim_scale(140.0) == 1.0
    assert dim_scale(0.8 * DAY_GREY) == pytest.approx(0.64)
    assert dim_scale(NIGHT_GREY) == MIN_DIM_SCALE
    pipe = VisionPipeline(parse_site(site_dict()))
    # each frame differs from the one before by more than a repeated frame may; at night (grey below
    # NIGHT_GREY) vehicles are found by their lights, which are not dimmed: the threshold stays
    for k, (grey, scale) in enumerate([(110, 1.0), (0.8 * DAY_GREY, 0.64), (NIGHT_GREY - 20, 1.0),
                                       (NIGHT_GREY + 5, MIN_DIM_SCALE)]):
        img = np.full((H, W), int(round(grey)), np.uint8)
        pipe.step(Frame(seq=k, t=k * 0.04, wall=1767225600.0 + k * 0.04, image=img))
        assert pipe.detector.scale == pytest.approx(scale), (grey, pipe.detector.scale)
