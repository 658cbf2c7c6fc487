"""Fitting and checking the image -> road homography from points and lane lines (no CLI here)."""

from __future__ import annotations

import csv
import io
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from appliance.geometry import CalibrationError, Homography
from appliance.zones import camera_from_homography, placed_camera

PLAUSIBLE_POINT_ERROR_M = 0.5


@dataclass
class LaneLine:
    """Image points on one lane marking, whose road X (across the road) is known."""

    px: list[list[float]]
    x_m: float


@dataclass
class Correspondences:
    image_px: list[list[float]] = field(default_factory=list)
    road_m: list[list[float]] = field(default_factory=list)
    lines: list[LaneLine] = field(default_factory=list)


@dataclass
class CalibrationResult:
    homography: Homography
    point_errors_m: np.ndarray  # per point pair, metres
    line_errors_m: list[np.ndarray]  # per lane line, |X(H p) - x_m| of each of its points
    warnings: list[str]
    image_px: list[list[float]]  # what to write into calibration.image_px
    road_m: list[list[float]]  # and calibration.road_m
    notes: list[str] = field(default_factory=list)  # worth knowing, not a reason to refuse

    def to_dict(self) -> dict:
        return {
            "homography_img_to_road": self.homography.H.tolist(),
            "point_errors_m": [round(float(e), 4) for e in self.point_errors_m],
            "line_errors_m": [[round(float(e), 4) for e in le] for le in self.line_errors_m],
            "mean_error_m": round(float(self.all_errors().mean()), 4) if self.all_errors().size else None,
            "max_error_m": round(float(self.all_errors().max()), 4) if self.all_errors().size else None,
            "warnings": self.warnings,
            "notes": self.notes,
            "image_px": self.image_px,
            "road_m": self.road_m,
        }

    def all_errors(self) -> np.ndarray:
        return np.concatenate([self.point_errors_m, *self.line_errors_m]) if self.line_errors_m else self.point_errors_m


def _normaliser(pts: np.ndarray) -> np.ndarray:
    """Hartley normalisation: centroid to 0, mean distance sqrt(2)."""
    c = pts.mean(axis=0)
    d = np.linalg.norm(pts - c, axis=1).mean()
    s = np.sqrt(2) / d if d > 1e-12 else 1.0
    return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])


def fit_homography(corr: Correspondences) -> Homography:
    """Direct linear transform over point pairs (2 equations each) and lane-line points (1 each)."""
    img = np.asarray(corr.image_px, dtype=np.float64).reshape(-1, 2)
    road = np.asarray(corr.road_m, dtype=np.float64).reshape(-1, 2)
    if len(img) != len(road):
        raise CalibrationError(f"{len(img)} image points but {len(road)} road points; they must pair up")
    line_px = [np.asarray(ln.px, dtype=np.float64).reshape(-1, 2) for ln in corr.lines]
    for i, lp in enumerate(line_px):
        if len(lp) < 2:
            raise CalibrationError(f"lane line {i + 1}: needs at least 2 image points")
    if not corr.lines:
        return Homography.from_points(img, road)
    if len(img) < 3 or np.ptp(road[:, 1]) < 1e-6:
        raise CalibrationError(
            "lane lines fix only X; give at least 3 points (not all at one road Y) for the scale along the road"
        )
    if len(img) < 4 and len({round(ln.x_m, 3) for ln in corr.lines}) < 3:
        raise CalibrationError(
            "lane lines at fewer than 3 different X do not fix the horizon: add a lane line or use 4 or more points"
        )
    n_eq = 2 * len(img) + sum(len(lp) for lp in line_px)
    if n_eq < 8:
        raise CalibrationError(f"too few constraints: {n_eq} equations, a homography needs 8")
    all_img = np.vstack([img, *line_px])
    all_road = np.vstack([road, np.column_stack([[ln.x_m for ln in corr.lines], np.zeros(len(corr.lines))])])
    Ti, Tr = _normaliser(all_img), _normaliser(all_road)
    ih = lambda p: (np.column_stack([p, np.ones(len(p))]) @ Ti.T)[:, :2]  # noqa: E731
    rows = []
    for (u, v), (X, Y) in zip(ih(img), (np.column_stack([road, np.ones(len(road))]) @ Tr.T)[:, :2]):
        rows.append([-u, -v, -1, 0, 0, 0, X * u, X * v, X])
        rows.append([0, 0, 0, -u, -v, -1, Y * u, Y * v, Y])
    for ln, lp in zip(corr.lines, line_px):
        Xn = Tr[0, 0] * ln.x_m + Tr[0, 2]
        for u, v in ih(lp):
            rows.append([-u, -v, -1, 0, 0, 0, Xn * u, Xn * v, Xn])
    A = np.asarray(rows)
    _, s, vt = np.linalg.svd(A)
    if len(s) < 8 or s[7] < 1e-9 * s[0]:
        raise CalibrationError("the points and lines do not determine a homography (degenerate layout)")
    Hn = vt[-1].reshape(3, 3)
    H = np.linalg.inv(Tr) @ Hn @ Ti
    if not np.all(np.isfinite(H)):
        raise CalibrationError("no homography fits these points and lines")
    return Homography.from_matrix(H)


def _collinearity(pts: np.ndarray) -> float:
    c = pts - pts.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    return float(s[-1] / max(s[0], 1e-12))


def check(
    H: Homography,
    corr: Correspondences,
    image_size: tuple[int, int] | None = None,
    zones_px: list[np.ndarray] | None = None,
    max_point_error_m: float = PLAUSIBLE_POINT_ERROR_M,
) -> CalibrationResult:
    """Reprojection errors and warnings about a degenerate or implausible calibration."""
    img = np.asarray(corr.image_px, dtype=np.float64).reshape(-1, 2)
    road = np.asarray(corr.road_m, dtype=np.float64).reshape(-1, 2)
    perr = H.reprojection_error_m(img, road) if len(img) else np.zeros(0)
    lerr = [np.abs(H.img_to_road(ln.px)[:, 0] - ln.x_m) for ln in corr.lines]
    warnings: list[str] = []
    for i, e in enumerate(perr):
        if e > max_point_error_m:
            warnings.append(f"point {i + 1} {img[i].tolist()} -> {road[i].tolist()}: error {e:.2f} m > {max_point_error_m} m (typo or wrong point?)")
    for i, le in enumerate(lerr):
        if le.size and le.max() > max_point_error_m:
            warnings.append(f"lane line {i + 1} (X = {corr.lines[i].x_m} m): error up to {le.max():.2f} m > {max_point_error_m} m")
    all_img = np.vstack([img, *[np.asarray(ln.px, float) for ln in corr.lines]]) if corr.lines else img
    if len(img) >= 3 and not corr.lines and (_collinearity(img) < 0.05 or _collinearity(road) < 0.05):
        warnings.append("the points lie nearly on one line: the calibration is poorly determined across it")
    w_img = all_img @ H.H[2, :2] + H.H[2, 2]
    if np.any(np.sign(w_img) != np.sign(w_img[0])):
        warnings.append("the horizon passes between the calibration points: some points are behind the camera")
    centre = all_img.mean(axis=0)
    d = 1.0
    J = np.column_stack([
        (H.img_to_road([centre + [d, 0]]) - H.img_to_road([centre - [d, 0]]))[0] / (2 * d),
        (H.img_to_road([centre + [0, d]]) - H.img_to_road([centre - [0, d]]))[0] / (2 * d),
    ])  # J[:, 0] = d(X, Y)/du, J[:, 1] = d(X, Y)/dv
    if np.linalg.det(J) > 0:
        warnings.append(
            "the calibration is mirror-flipped: X must grow to the right in the image and Y away from the camera "
            "(upwards in the image); check the sign of road_m X or Y"
        )
    elif J[1, 1] > 0:
        warnings.append("road Y grows towards the camera (down the image); Y must grow away from the camera")
    p_top, p_bottom = all_img[np.argmin(all_img[:, 1])], all_img[np.argmax(all_img[:, 1])]
    if p_bottom[1] - p_top[1] > 1.0:
        scale = H.metres_per_pixel(np.array([p_top, p_bottom]))[:, 1]
        if scale[0] < scale[1]:
            warnings.append(
                "inverted perspective: the scale shrinks towards the top of the image, so lines parallel on "
                "the road diverge; a point is probably wrong"
            )
    notes = []
    if not corr.lines and len(img) == 4:
        notes.append("exactly 4 points fit exactly (errors are 0 by construction); add points to check for typos")
    if image_size is not None:
        w, h = image_size
        bbox = np.ptp(all_img, axis=0)
        if bbox[0] * bbox[1] < 0.05 * w * h:
            warnings.append(f"the points cover only {100 * bbox[0] * bbox[1] / (w * h):.1f} % of the image; spread them over the road")
        horizon = [H.horizon_row(0.0), H.horizon_row(float(w - 1))]
        zones = zones_px or []
        sign_ref = np.sign(w_img[0])
        for z in zones:
            wz = np.asarray(z, float) @ H.H[2, :2] + H.H[2, 2]
            if np.any(np.sign(wz) != sign_ref):
                warnings.append("the horizon runs through a lane or zone: part of it is above the horizon")
                break
        else:
            if zones and all(r is not None for r in horizon):
                top = min(float(np.asarray(z, float)[:, 1].min()) for z in zones)
                hmax = max(horizon)
                if sign_ref > 0 and 0 <= top - hmax < 0.05 * h:
                    warnings.append(
                        f"a lane or zone reaches row {top:.0f}, within {top - hmax:.0f} px of the horizon (row {hmax:.0f}): "
                        "distances there are very uncertain"
                    )
        probe = np.array([[w / 2, h - 1]])
        mpp = H.metres_per_pixel(probe)[0]
        if not 0.002 < mpp.max() < 1.0:
            warnings.append(f"implausible scale at the image bottom: {mpp.max():.3f} m per pixel")
        cam, placed = camera_from_homography(H, w, h), placed_camera(H, w, h)
        if cam is not None:
            notes.append(f"camera about {cam[2]:.1f} m above the road, its foot at X {cam[0]:.1f} m, Y {cam[1]:.1f} m: "
                         "the tracker undoes vehicle heights")
            if placed is not None and abs(placed[3] - (w - 1) / 2) > 0.5:
                notes.append(f"the lens's axis seems to be at column {placed[3]:.0f}, not the frame's centre "
                             f"({(w - 1) / 2:.0f}): a frame cropped from a wider picture? The camera above, placed "
                             f"from the centre, is then askew (from the column: {placed[2]:.1f} m up, its foot at X "
                             f"{placed[0]:.1f} m, Y {placed[1]:.1f} m); the uncropped picture avoids that")
        elif placed is not None:
            notes.append(f"a camera about {placed[2]:.1f} m above the road fits only with its lens's axis at column "
                         f"{placed[3]:.0f}, not the frame's centre ({(w - 1) / 2:.0f}): a frame cropped from a wider "
                         "picture (or an along-road scale somewhat out). The tracker works without vehicle heights, "
                         "so roofs may be reported apart from their vehicles (lengths are measured with this camera); "
                         "the uncropped picture avoids that")
        else:
            notes.append("no camera on a pole or overpass fits this calibration (an along-road scale far out?): the "
                         "tracker works without vehicle heights, so roofs may be reported apart from their vehicles "
                         "and lengths read long")
    # the file form: the given points, plus lane-line points with their fitted road positions
    out_img = [list(map(float, p)) for p in img]
    out_road = [list(map(float, p)) for p in road]
    for ln in corr.lines:
        pts = np.asarray(ln.px, float)
        r = H.img_to_road(pts)
        r[:, 0] = ln.x_m
        out_img += pts.tolist()
        out_road += r.tolist()
    return CalibrationResult(H, perr, lerr, warnings, out_img, out_road, notes)


def parse_point(text: str) -> tuple[list[float], list[float]]:
    """'u,v=X,Y' -> ([u, v], [X, Y])."""
    try:
        a, b = text.split("=")
        u, v = (float(x) for x in a.split(","))
        X, Y = (float(x) for x in b.split(","))
    except ValueError:
        raise ValueError(f"point {text!r}: expected 'u,v=X,Y' (image pixels = road metres)") from None
    return [u, v], [X, Y]


def parse_lane_line(text: str, default_x: float | None) -> LaneLine:
    """'u,v u,v ...[=X]' -> LaneLine; without '=X' the X comes from the lane width."""
    spec, _, x = text.partition("=")
    pts = []
    for p in spec.replace(";", " ").split():
        try:
            u, v = (float(c) for c in p.split(","))
        except ValueError:
            raise ValueError(f"lane line {text!r}: {p!r} is not 'u,v'") from None
        pts.append([u, v])
    if x.strip():
        try:
            xm = float(x)
        except ValueError:
            raise ValueError(f"lane line {text!r}: X {x!r} is not a number") from None
    elif default_x is None:
        raise ValueError(f"lane line {text!r}: give its road X ('...=X') or --lane-width")
    else:
        xm = default_x
    if len(pts) < 2:
        raise ValueError(f"lane line {text!r}: needs at least 2 image points")
    return LaneLine(pts, xm)


def read_points_file(path: str | Path) -> Correspondences:
    """Correspondences from CSV (u,v,x,y per row), JSON or TOML (image_px/road_m lists,
    optional lane_lines [{px, x_m}], or a site config's [calibration] table)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise ValueError(f"{p}: cannot be read ({e.strerror})") from None
    suffix = p.suffix.lower()
    if suffix == ".csv":
        corr = Correspondences()
        for n, row in enumerate(csv.reader(io.StringIO(text)), start=1):
            if not row or not "".join(row).strip() or row[0].strip().startswith("#"):
                continue
            try:
                u, v, x, y = (float(c) for c in row[:4])
            except ValueError:
                if n == 1:
                    continue  # header
                raise ValueError(f"{p}:{n}: expected u,v,x,y numbers, got {row}") from None
            corr.image_px.append([u, v])
            corr.road_m.append([x, y])
        return corr
    try:
        data = json.loads(text) if suffix == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as e:
        raise ValueError(f"{p}: cannot be parsed ({e})") from None
    if isinstance(data, dict) and "calibration" in data and "image_px" not in data:
        data = data["calibration"]
    if not isinstance(data, dict):
        raise ValueError(f"{p}: expected a table with image_px and road_m")
    try:
        lines = [LaneLine([list(map(float, q)) for q in ln["px"]], float(ln["x_m"])) for ln in data.get("lane_lines", [])]
        return Correspondences(
            [list(map(float, q)) for q in data.get("image_px", [])],
            [list(map(float, q)) for q in data.get("road_m", [])],
            lines,
        )
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{p}: malformed calibration data ({e})") from None
