"""Site configuration: loading, defaults, derived geometry, and errors that name the key."""

from __future__ import annotations

import json

import numpy as np
import pytest

from appliance.config import ConfigError, parse_site


def _site() -> dict:
    # A 2-lane road seen from 8 m up; calibration from a known homography.
    return {
        "site": {"name": "test"},
        "source": {"width": 640, "height": 480, "fps": 25.0},
        "calibration": {
            "image_px": [[200, 400], [440, 400], [280, 200], [360, 200]],
            "road_m": [[-3.5, 10.0], [3.5, 10.0], [-3.5, 50.0], [3.5, 50.0]],
        },
        "lanes": [
            {"id": 1, "direction": "approaching", "polygon_m": [[-3.5, 12], [0, 12], [0, 48], [-3.5, 48]]},
            {"id": 2, "direction": "receding", "polygon_m": [[0, 12], [3.5, 12], [3.5, 48], [0, 48]]},
        ],
        "loops": [
            {"id": "L1", "lane": 1, "channel": 1, "y_m": 20.0, "length_m": 2.0},
            {"id": "L2", "lane": 2, "channel": 2, "y_m": 20.0},
        ],
    }


def test_valid_site_derives_geometry() -> None:
    cfg = parse_site(_site())
    assert cfg.homography is not None
    err = cfg.homography.reprojection_error_m(cfg.calibration.image_px, cfg.calibration.road_m)
    assert err.max() < 1e-6
    lane = cfg.lane(1)
    assert lane.region_y_m == [12.0, 48.0] and lane.count_y_m == 30.0
    loop = cfg.loops[0]
    poly = np.asarray(loop.polygon_m)
    assert poly[:, 1].min() == pytest.approx(20.0) and poly[:, 1].max() == pytest.approx(22.0)
    assert poly[:, 0].min() == pytest.approx(-3.5) and poly[:, 0].max() == pytest.approx(0.0)
    assert cfg.loops[1].length_m == pytest.approx(1.8)


@pytest.mark.parametrize(
    "mutate, key",
    [
        (lambda d: d["lanes"][0].update(direction="sideways"), "lanes[0].direction"),
        (lambda d: d["loops"][1].update(channel=1), "loops[1].channel"),
        (lambda d: d["loops"][0].update(lane=9), "loops[0].lane"),
        (lambda d: d["source"].update(fps="fast"), "source.fps"),
        (lambda d: d["source"].update(fsp=25), "source.fsp"),
        (lambda d: d["calibration"].update(image_px=[[0, 0], [1, 1], [2, 2], [3, 3]]), "calibration"),
        (lambda d: d["lanes"][0].update(polygon_m=[[-3.5, 2], [0, 2], [0, 48], [-3.5, 48]]), "lanes[0]"),
        (lambda d: d["measures"].update(period_s=7) if "measures" in d else d.update(measures={"period_s": 7}), "measures.period_s"),
    ],
)
def test_bad_config_names_the_key(mutate, key) -> None:
    d = json.loads(json.dumps(_site()))
    mutate(d)
    with pytest.raises(ConfigError) as exc:
        parse_site(d, "site.toml")
    assert exc.value.key == key, str(exc.value)
    assert str(exc.value).startswith("site.toml: " + key)


def test_unknown_key_suggests_the_right_one() -> None:
    d = _site()
    d["source"]["fsp"] = 25
    with pytest.raises(ConfigError, match="did you mean 'fps'"):
        parse_site(d)
