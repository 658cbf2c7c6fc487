"""The camera's foot and height recovered from a site's calibration (appliance.zones.camera_from_homography)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from appliance.geometry import Homography
from appliance.zones import camera_from_homography, placed_camera
from tools.simulate.camera import Camera

# a calibration as installers click it: three lines across the road at three distances
ROAD = np.array([(x, y) for y in (15.0, 45.0, 90.0) for x in (-3.5, 0.0, 3.5)])


def _clicked(cam: Camera, sigma_px: float, rng: np.random.Generator) -> Homography:
    img = cam.road_to_image(ROAD) + rng.normal(0.0, sigma_px, (len(ROAD), 2))
    return Homography.from_points(img, ROAD)


@pytest.mark.parametrize("pan", [8.5, 0.0])
def test_the_camera_is_recovered_from_an_exact_calibration(pan):
    cam = Camera(height_m=12.0, tilt_deg=16.0, pan_deg=pan, x_m=9.0 if pan else 0.0)
    foot_x, foot_y, h = camera_from_homography(_clicked(cam, 0.0, np.random.default_rng(0)), 640, 480)
    # the simulator's principal point is the image centre to half a pixel
    assert abs(h - 12.0) < 0.1 and abs(foot_x - cam.x_m) < 0.1 and abs(foot_y) < 0.2


def test_click_errors_move_the_camera_little():
    """Half a pixel of click error on each point: the height within 0.8 m of 12 m in 90 % of calibrations.
    (Taking the focal length from the two axes' orthogonality alone, as before, moved it 9.4-13.1 m; that
    constraint's terms shrink with the pan and click errors swamp them.)"""
    cam = Camera(height_m=12.0, tilt_deg=16.0, pan_deg=8.5, x_m=9.0)
    rng = np.random.default_rng(3)
    cams = [camera_from_homography(_clicked(cam, 0.5, rng), 640, 480) for _ in range(60)]
    heights = np.array([c[2] if c is not None else np.nan for c in cams])
    assert np.mean(np.abs(heights - 12.0) < 0.8) >= 0.9, np.round(heights, 2)


def test_a_frame_cropped_beside_the_lens_axis_still_places_the_camera():
    """A frame cut from a wider picture (its principal point 150 px right of its centre): the centred camera
    fits it only askew (its height 0.2 m out, its foot 1.8 m); the column that fits places it exactly."""
    cam = Camera(height_m=12.0, tilt_deg=16.0, pan_deg=8.5, x_m=9.0)
    img = cam.road_to_image(ROAD) - [150.0, 0.0]  # the frame's columns 150..789 of the 940-wide picture
    H = Homography.from_points(img, ROAD)
    foot_x, foot_y, h, col = placed_camera(H, 640, 480)
    assert abs(h - 12.0) < 0.1 and abs(foot_x - cam.x_m) < 0.1 and abs(foot_y) < 0.2 and abs(col - 169.5) < 1.0
    centred = camera_from_homography(H, 640, 480)
    assert centred is not None and abs(centred[1]) > 1.0


def test_click_errors_do_not_make_a_crop():
    """Half a pixel of click error moves the column that fits (up to 0.06 of the width): the centred camera
    stays the one placed."""
    cam = Camera(height_m=12.0, tilt_deg=16.0, pan_deg=8.5, x_m=9.0)
    rng = np.random.default_rng(3)
    for _ in range(30):
        H = _clicked(cam, 0.5, rng)
        assert placed_camera(H, 640, 480) == (*camera_from_homography(H, 640, 480), 319.5)


def test_a_calibration_no_camera_fits_gives_no_camera():
    """An along-road scale three times too long (a misread dash cycle): no principal point inside the frame
    fits a camera, and the tracker works without heights."""
    cam = Camera(height_m=12.0, tilt_deg=16.0, pan_deg=8.5, x_m=9.0)
    H = Homography.from_points(cam.road_to_image(ROAD), ROAD * [1.0, 3.0])
    assert camera_from_homography(H, 640, 480) is None and placed_camera(H, 640, 480) is None


def test_the_real_clip_places_its_camera_from_the_column_that_fits(shared_data):
    """The real clip's calibration (lane markings, an assumed dash cycle): a camera looking along the road whose
    principal point is not the image centre, the frame likely a crop. No centred camera fits it (the tracker
    works without heights); the column that fits, x 276, is where padding the frame to centre it puts it, and
    both place the same camera, about 8 m up."""
    p = shared_data / "cdnet-highway" / "counts.json"
    if not p.exists():
        pytest.skip("cdnet-highway/counts.json missing")
    cal = json.loads(p.read_text())["calibration"]
    H = Homography.from_points(cal["image_px"], cal["road_m"])
    assert camera_from_homography(H, 320, 240) is None
    cam, padded = placed_camera(H, 320, 240), camera_from_homography(H, 552, 240)
    assert cam is not None and padded is not None and 7.0 < cam[2] < 9.5 and abs(cam[3] - 275.9) < 1.0, cam
    assert np.allclose(cam[:3], padded, atol=0.05), (cam, padded)
