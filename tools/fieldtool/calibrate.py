"""`roadwatch calibrate`: fit the camera homography, report its error, draw a metre grid, write it."""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from appliance.geometry import CalibrationError
from tools.fieldtool.calibration_fit import (
    Correspondences,
    check,
    fit_homography,
    parse_lane_line,
    parse_point,
    read_points_file,
)
from tools.fieldtool.common import config_option, source_only_config, url_option, write_png
from tools.fieldtool.config_cmd import install_config


def _raw_config(path: str) -> dict:
    import tomllib

    p = Path(path)
    if not p.exists():
        return {}
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise click.ClickException(f"{p}: cannot be read as TOML ({e})") from None


def _read_image(path: str) -> np.ndarray:
    import cv2

    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        raise click.ClickException(f"{path}: not a readable image")
    return img


def _zones_px(raw: dict, H) -> list[np.ndarray]:
    """Lane polygons of the config in pixels under the new homography (for the horizon check)."""
    zones = []
    for lane in raw.get("lanes", []):
        if lane.get("polygon_px"):
            zones.append(np.asarray(lane["polygon_px"], float))
        elif lane.get("polygon_m"):
            zones.append(H.road_to_img(np.asarray(lane["polygon_m"], float)))
    return zones


@click.command("calibrate")
@config_option
@click.option("--points", "points_file", type=click.Path(exists=True, dir_okay=False),
              help="Correspondences: CSV rows u,v,x,y; or JSON/TOML with image_px, road_m [, lane_lines].")
@click.option("--point", "points", multiple=True, metavar="U,V=X,Y",
              help="One correspondence: image pixel = road metres (repeatable).")
@click.option("--lane-line", "lane_lines", multiple=True, metavar="'U,V U,V ...[=X]'",
              help="Image points on one lane marking whose road X is known (repeatable, left to right).")
@click.option("--lane-width", type=float, default=None,
              help="Lane width in m: lane lines without '=X' get X = --first-line-x + i * width.")
@click.option("--first-line-x", type=float, default=0.0, show_default=True, help="Road X of the first lane line.")
@click.option("--snapshot", type=click.Path(exists=True, dir_okay=False), help="Snapshot PNG to draw the grid on.")
@click.option("--grid", "grid_out", type=click.Path(dir_okay=False), help="Write a PNG with the metre grid.")
@click.option("--grid-step", type=(float, float), default=(1.0, 5.0), show_default=True,
              help="Grid spacing across (X) and along (Y) the road, metres.")
@click.option("--grid-x", type=(float, float), default=None, help="Grid X range, m (default: from the points).")
@click.option("--grid-y", type=(float, float), default=None, help="Grid Y range, m (default: from the points).")
@click.option("--write", is_flag=True, help="Write the calibration into the config (validated, atomic).")
@click.option("--force", is_flag=True, help="With --write: write even if there are warnings.")
@click.option("--reload/--no-reload", default=True, show_default=True, help="With --write: reload the running service.")
@url_option
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def calibrate(config_path: str, points_file: str | None, points: tuple[str, ...], lane_lines: tuple[str, ...],
              lane_width: float | None, first_line_x: float, snapshot: str | None, grid_out: str | None,
              grid_step: tuple[float, float], grid_x: tuple[float, float] | None, grid_y: tuple[float, float] | None,
              write: bool, force: bool, reload: bool, url: str | None, as_json: bool) -> None:
    """Fit the image -> road homography, report the error in metres per point, draw a grid.

    Road metres: X across the road (growing to the right in the image), Y along the road
    (growing away from the camera). At least 4 points, or 3 points plus lane lines at 3 or more X.

    \b
    Examples:
      roadwatch calibrate --points marks.csv --grid grid.png --snapshot snap.png
      roadwatch calibrate --point 130,217=0,0 --point 252,217=3.66,0 \\
          --point 160,160=0,12.2 --point 258,160=3.66,12.2 --write
      roadwatch calibrate --lane-line "0,214 177,40=-3.94" --lane-line "130,217 204,79=0" \\
          --lane-line "252,217 265,79=3.66" \\
          --point 130,217=0,0 --point 160,160=0,12.2 --point 262,98=3.66,36.6
    """
    raw = _raw_config(config_path)
    corr = Correspondences()
    try:
        if points_file:
            corr = read_points_file(points_file)
        for p in points:
            a, b = parse_point(p)
            corr.image_px.append(a)
            corr.road_m.append(b)
        for i, text in enumerate(lane_lines):
            default_x = first_line_x + i * lane_width if lane_width is not None else None
            corr.lines.append(parse_lane_line(text, default_x))
    except ValueError as e:
        raise click.ClickException(str(e)) from None
    if not corr.image_px and not corr.lines:
        if raw.get("calibration", {}).get("image_px"):
            cal = raw["calibration"]
            corr.image_px, corr.road_m = cal["image_px"], cal.get("road_m", [])
            if not as_json:
                click.echo(f"checking the calibration in {config_path}")
        else:
            raise click.ClickException("no correspondences: give --points FILE, --point U,V=X,Y or --lane-line")
    try:
        H = fit_homography(corr)
    except CalibrationError as e:
        raise click.ClickException(f"calibration failed: {str(e).removeprefix('calibration: ')}") from None

    src = raw.get("source", {})
    size = (int(src.get("width", 640)), int(src.get("height", 480)))
    if not raw and snapshot:  # no config yet: the snapshot gives the image size
        h, w = _read_image(snapshot).shape[:2]
        size = (w, h)
    limit = float(raw.get("calibration", {}).get("max_error_m", 0.5))
    result = check(H, corr, size, _zones_px(raw, H), max_point_error_m=limit)

    if as_json:
        click.echo(json.dumps(result.to_dict(), indent=2))
    else:
        click.echo(f"{'#':>3} {'u':>8} {'v':>8} {'X m':>8} {'Y m':>8} {'error m':>8}")
        for i, ((u, v), (X, Y), e) in enumerate(zip(corr.image_px, corr.road_m, result.point_errors_m), 1):
            click.echo(f"{i:>3} {u:8.1f} {v:8.1f} {X:8.2f} {Y:8.2f} {e:8.3f}")
        for i, (ln, le) in enumerate(zip(corr.lines, result.line_errors_m), 1):
            click.echo(f"lane line {i}: X = {ln.x_m:.2f} m, {len(ln.px)} points, error mean {le.mean():.3f} max {le.max():.3f} m")
        errs = result.all_errors()
        click.echo(f"reprojection error: mean {errs.mean():.3f} m, max {errs.max():.3f} m")
        hr = H.horizon_row(size[0] / 2)
        if hr is not None:
            click.echo(f"horizon at image row {hr:.0f} (centre column)")
        mpp = H.metres_per_pixel([[size[0] / 2, size[1] - 1]])[0]
        click.echo(f"scale at the image bottom: {100 * mpp[0]:.1f} cm/px across, {100 * mpp[1]:.1f} cm/px along")
        for n in result.notes:
            click.echo(f"note: {n}")
        for w in result.warnings:
            click.echo(f"WARNING: {w}", err=True)
        if not result.warnings:
            click.echo("no warnings")

    if grid_out:
        from tools.fieldtool.overlay import draw_calibration_points, draw_grid
        from tools.fieldtool.snapshot import base_image

        road = np.asarray(result.road_m, float)
        gx = grid_x or (float(np.floor(road[:, 0].min())) - 1, float(np.ceil(road[:, 0].max())) + 1)
        gy = grid_y or (float(np.floor(road[:, 1].min())), float(np.ceil(road[:, 1].max())))
        if raw:
            img = base_image(source_only_config(config_path), snapshot)
        elif snapshot:
            img = _read_image(snapshot)
        else:
            from tools.fieldtool.overlay import blank

            img = blank(*size)
        img = draw_grid(img, H, gx, gy, grid_step[0], grid_step[1])
        img = draw_calibration_points(img, result.image_px, np.concatenate([result.point_errors_m, *result.line_errors_m]))
        write_png(grid_out, img)
        if not as_json:
            click.echo(f"wrote {grid_out}: grid X {gx[0]:g}..{gx[1]:g} m every {grid_step[0]:g}, Y {gy[0]:g}..{gy[1]:g} m every {grid_step[1]:g}")

    if write:
        if result.warnings and not force:
            raise click.ClickException("not written: fix the warnings above or use --force")
        if not raw:
            raise click.ClickException(f"{config_path}: no config to write into (make one first, e.g. from config/)")
        data = dict(raw)
        cal = dict(data.get("calibration", {}))
        cal["image_px"] = [[round(float(a), 3) for a in p] for p in result.image_px]
        cal["road_m"] = [[round(float(a), 4) for a in p] for p in result.road_m]
        data["calibration"] = cal
        res = install_config(config_path, data, url, reload, draft_ok=True)
        for line in res.lines(config_path):
            click.echo(line, err=as_json)
