"""`roadwatch zones`: define lanes, detection/exit zones, fiducials and loops; draw and check them."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from appliance.config import SiteConfig
from appliance.geometry import polygon_contains
from tools.fieldtool.common import (
    config_option,
    load_config,
    parse_polygon,
    parse_xy,
    read_toml,
    url_option,
    validate_dict,
    write_file,
    write_png,
)
from tools.fieldtool.config_cmd import install_config
from tools.fieldtool.overlay import draw_site, lane_polygons_px, loop_polygons_px


def zone_warnings(cfg: SiteConfig) -> list[str]:
    """Problems parse_site accepts but an installer should look at."""
    out = []
    lanes_px = lane_polygons_px(cfg)
    for i, f in enumerate(cfg.fiducials):
        for lane_id, poly in lanes_px.items():
            if polygon_contains(poly, [f])[0]:
                out.append(f"fiducial F{i + 1} {f} is on lane {lane_id}: vehicles will cover it; pick a static spot off the road")
    if cfg.tracking.stabilise and len(cfg.fiducials) < 2:
        out.append(f"tracking.stabilise is on but only {len(cfg.fiducials)} fiducial(s) are set (2-4 recommended)")
    loops = cfg.loops
    for a in range(len(loops)):
        for b in range(a + 1, len(loops)):
            la, lb = loops[a], loops[b]
            if la.lane == lb.lane and la.y_m < lb.y_m + lb.length_m and lb.y_m < la.y_m + la.length_m:
                out.append(f"loops {la.id} and {lb.id} overlap in lane {la.lane}")
    for lp in loops:
        if lp.trap_with:
            other = next(x for x in loops if x.id == lp.trap_with)
            if other.lane != lp.lane:
                out.append(f"speed trap {lp.id}/{other.id} spans two lanes ({lp.lane}, {other.lane})")
    for lane in cfg.lanes:
        if lane.detection_y_m and lane.exit_y_m:
            d, e = lane.detection_y_m, lane.exit_y_m
            if d[0] < e[1] and e[0] < d[1]:
                out.append(f"lane {lane.id}: detection zone {d} and exit zone {e} overlap")
            elif (d[0] < e[0]) == (lane.direction == "approaching"):
                where = "far (larger Y)" if lane.direction == "approaching" else "near (smaller Y)"
                out.append(f"lane {lane.id} is {lane.direction}: vehicles enter at the {where} end, "
                           f"but the detection zone {d} is past the exit zone {e}")
    return out


def summary(cfg: SiteConfig) -> list[str]:
    from appliance.zones import SiteZones

    lines = []
    lanes_px = lane_polygons_px(cfg)
    eff = {lz.lane_id: lz for lz in SiteZones(cfg).lanes}
    for lane in cfg.lanes:
        lz = eff[lane.id]
        det = f"{lz.detection_y[0]:.1f}..{lz.detection_y[1]:.1f} m" + ("" if lane.detection_y_m else " (default)")
        ext = f"{lz.exit_y[0]:.1f}..{lz.exit_y[1]:.1f} m" + ("" if lane.exit_y_m else " (default)")
        poly = np.asarray(lane.polygon_m)
        lines.append(
            f"lane {lane.id} {lane.direction}: X {poly[:, 0].min():.1f}..{poly[:, 0].max():.1f} m, "
            f"Y {poly[:, 1].min():.1f}..{poly[:, 1].max():.1f} m, image rows "
            f"{lanes_px[lane.id][:, 1].min():.0f}..{lanes_px[lane.id][:, 1].max():.0f}; "
            f"count at Y {lane.count_y_m:.1f} m; detection {det}; exit {ext}"
        )
    loops_px = loop_polygons_px(cfg)
    for lp in sorted(cfg.loops, key=lambda x: x.channel):
        c = loops_px[lp.id].mean(axis=0)
        lines.append(
            f"channel {lp.channel:>3} <- loop {lp.id} lane {lp.lane} {lp.mode}: Y {lp.y_m:.1f}..{lp.y_m + lp.length_m:.1f} m "
            f"(image ~{c[0]:.0f},{c[1]:.0f})" + (f", speed trap with {lp.trap_with}" if lp.trap_with else "")
        )
    for i, f in enumerate(cfg.fiducials):
        lines.append(f"fiducial F{i + 1} at pixel {f[0]:.0f},{f[1]:.0f}")
    return lines


def render(cfg: SiteConfig, snapshot: str | None, out: str) -> None:
    from tools.fieldtool.snapshot import base_image

    img = draw_site(base_image(cfg, snapshot), cfg)
    write_png(out, img)


@click.group("zones")
def zones() -> None:
    """Define lanes, detection/exit zones, fiducials and virtual loops; draw and check them.

    Edits validate the whole config (zones inside the image, loops inside lanes, channels
    unique), write it atomically (the previous good file is kept as CONFIG.last-good) and
    reload the running service. Geometry in image pixels (*-px) or road metres (*-m).

    \b
    Examples:
      roadwatch zones lane 1 --direction approaching --polygon-px "177,40 224,40 118,239 0,239 0,214"
      roadwatch zones loop L1 --lane 1 --channel 1 --y-m 6.3 --length-m 4.5
      roadwatch zones fiducials 40,30 300,200
      roadwatch zones render --snapshot snap.png --out zones.png
      roadwatch zones check
    """


def _edit_options(f):
    f = click.option("--out", "out_config", type=click.Path(dir_okay=False),
                     help="Write the edited config here instead of replacing CONFIG.")(f)
    f = click.option("--render", "render_png", type=click.Path(dir_okay=False), help="Also draw the result to this PNG.")(f)
    f = click.option("--snapshot", type=click.Path(exists=True, dir_okay=False), help="Snapshot to draw on.")(f)
    f = click.option("--reload/--no-reload", default=True, show_default=True, help="Reload the running service.")(f)
    f = url_option(f)
    f = config_option(f)
    return f


def _save(config_path: str, data: dict, out_config: str | None, url: str | None, reload: bool,
          render_png: str | None, snapshot: str | None) -> None:
    if out_config:
        cfg = validate_dict(data, str(Path(out_config)))
        import tomli_w

        write_file(out_config, tomli_w.dumps(data))
        click.echo(f"wrote {out_config}")
    else:
        for line in install_config(config_path, data, url, reload, draft_ok=True).lines(config_path):
            click.echo(line)
        if not data.get("lanes"):
            return  # a site still being set up: nothing to check or draw yet
        cfg = load_config(config_path)
    for w in zone_warnings(cfg):
        click.echo(f"WARNING: {w}", err=True)
    if render_png:
        render(cfg, snapshot, render_png)
        click.echo(f"wrote {render_png}")


def rows_to_y(config_path: str, lane_id: int, rows: tuple[float, float]) -> tuple[float, float]:
    """Two image rows -> the along-road range they cut from the lane (at the lane's centre column)."""
    cfg = load_config(config_path)
    try:
        lane = cfg.lane(lane_id)
    except KeyError:
        raise click.UsageError(f"--*-rows need lane {lane_id} to exist first (give its polygon)") from None
    H = cfg.homography
    cx = float(H.road_to_img(np.asarray(lane.polygon_m))[:, 0].mean())
    ys = H.img_to_road([[cx, rows[0]], [cx, rows[1]]])[:, 1]
    return float(round(ys.min(), 2)), float(round(ys.max(), 2))


def _range(value: tuple[float, float] | None) -> list[float] | None:
    return None if value is None else [float(value[0]), float(value[1])]


@zones.command("lane")
@click.argument("lane_id", type=int)
@click.option("--direction", type=click.Choice(["approaching", "receding"]))
@click.option("--polygon-px", help="Lane outline in image pixels: 'u,v u,v u,v ...'.")
@click.option("--polygon-m", help="Lane outline in road metres: 'x,y x,y x,y ...'.")
@click.option("--detection-y", type=(float, float), default=None, help="Detection zone Y0 Y1 (m) along the lane.")
@click.option("--exit-y", type=(float, float), default=None, help="Exit zone Y0 Y1 (m) along the lane.")
@click.option("--detection-rows", type=(float, float), default=None,
              help="Detection zone as two image rows (pixels), converted to Y at the lane's centre.")
@click.option("--exit-rows", type=(float, float), default=None, help="Exit zone as two image rows (pixels).")
@click.option("--region-y", type=(float, float), default=None, help="Edie measurement region Y0 Y1 (m).")
@click.option("--count-y", type=float, default=None, help="Count position Y (m).")
@_edit_options
def lane_cmd(lane_id: int, direction: str | None, polygon_px: str | None, polygon_m: str | None,
             detection_y: tuple[float, float] | None, exit_y: tuple[float, float] | None,
             detection_rows: tuple[float, float] | None, exit_rows: tuple[float, float] | None,
             region_y: tuple[float, float] | None, count_y: float | None, config_path: str, url: str | None,
             reload: bool, snapshot: str | None, render_png: str | None, out_config: str | None) -> None:
    """Add lane LANE_ID or change what is given of it.

    \b
    Example:
      roadwatch zones lane 2 --polygon-m "0,-3 3.66,-3 3.66,60 0,60" --detection-y 40 60 --exit-y -3 5
    """
    if polygon_px and polygon_m:
        raise click.UsageError("give --polygon-px or --polygon-m, not both")
    if detection_rows or exit_rows:
        detection_y = rows_to_y(config_path, lane_id, detection_rows) if detection_rows else detection_y
        exit_y = rows_to_y(config_path, lane_id, exit_rows) if exit_rows else exit_y
    data = read_toml(config_path)
    lanes = data.setdefault("lanes", [])
    lane = next((x for x in lanes if x.get("id") == lane_id), None)
    if lane is None:
        if not (polygon_px or polygon_m):
            raise click.UsageError(f"lane {lane_id} is new: give its --polygon-px or --polygon-m")
        lane = {"id": lane_id, "direction": direction or "approaching"}
        lanes.append(lane)
    if direction:
        lane["direction"] = direction
    if polygon_px or polygon_m:
        lane.pop("polygon_px", None)
        lane.pop("polygon_m", None)
        key = "polygon_px" if polygon_px else "polygon_m"
        lane[key] = parse_polygon(polygon_px or polygon_m, f"--{key.replace('_', '-')}")
    for key, val in (("detection_y_m", _range(detection_y)), ("exit_y_m", _range(exit_y)), ("region_y_m", _range(region_y))):
        if val is not None:
            lane[key] = val
    if count_y is not None:
        lane["count_y_m"] = count_y
    _save(config_path, data, out_config, url, reload, render_png, snapshot)


@zones.command("loop")
@click.argument("loop_id")
@click.option("--lane", type=int, help="Lane the loop is in.")
@click.option("--channel", type=int, help="Controller channel (1-based, unique).")
@click.option("--y-m", type=float, help="Along-road start of the loop (m); with --length-m.")
@click.option("--length-m", type=float, help="Loop length along the road (m; default 1.8).")
@click.option("--polygon-px", help="Loop outline in image pixels: 'u,v u,v u,v ...'.")
@click.option("--polygon-m", help="Loop outline in road metres.")
@click.option("--mode", type=click.Choice(["presence", "pulse"]))
@click.option("--trap-with", help="Id of the second loop of a speed trap.")
@_edit_options
def loop_cmd(loop_id: str, lane: int | None, channel: int | None, y_m: float | None, length_m: float | None,
             polygon_px: str | None, polygon_m: str | None, mode: str | None, trap_with: str | None, config_path: str,
             url: str | None, reload: bool, snapshot: str | None, render_png: str | None,
             out_config: str | None) -> None:
    """Add loop LOOP_ID or change it (lane, channel, position, mode, speed trap).

    \b
    Examples:
      roadwatch zones loop L3 --lane 1 --channel 3 --y-m 20 --length-m 1.8 --trap-with L1
      roadwatch zones loop L1 --channel 5
    """
    if sum(x is not None for x in (y_m, polygon_px, polygon_m)) > 1:
        raise click.UsageError("give one of --y-m, --polygon-px, --polygon-m")
    data = read_toml(config_path)
    loops = data.setdefault("loops", [])
    lp = next((x for x in loops if x.get("id") == loop_id), None)
    if lp is None:
        missing = [n for n, v in (("--lane", lane), ("--channel", channel)) if v is None]
        if y_m is None and polygon_px is None and polygon_m is None:
            missing.append("--y-m/--polygon-px/--polygon-m")
        if missing:
            raise click.UsageError(f"loop {loop_id} is new: give {', '.join(missing)}")
        lp = {"id": loop_id}
        loops.append(lp)
    for key, val in (("lane", lane), ("channel", channel), ("mode", mode), ("trap_with", trap_with)):
        if val is not None:
            lp[key] = val
    if y_m is not None or polygon_px or polygon_m:
        for k in ("y_m", "polygon_px", "polygon_m"):
            lp.pop(k, None)
        if y_m is not None:
            lp["y_m"] = y_m
        elif polygon_px:
            lp["polygon_px"] = parse_polygon(polygon_px, "--polygon-px")
        else:
            lp["polygon_m"] = parse_polygon(polygon_m, "--polygon-m")
    if length_m is not None:
        lp["length_m"] = length_m
    _save(config_path, data, out_config, url, reload, render_png, snapshot)


@zones.command("fiducials")
@click.argument("points", nargs=-1)
@click.option("--add", is_flag=True, help="Append to the list instead of replacing it.")
@_edit_options
def fiducials_cmd(points: tuple[str, ...], add: bool, config_path: str, url: str | None, reload: bool,
                  snapshot: str | None, render_png: str | None, out_config: str | None) -> None:
    """Set the fiducial points (image pixels 'u,v'; static, textured, off the road); none = clear.

    \b
    Example:
      roadwatch zones fiducials 40,30 300,200
    """
    data = read_toml(config_path)
    pts = [list(parse_xy(p, "fiducial")) for p in points]
    data["fiducials"] = (data.get("fiducials", []) + pts) if add else pts
    _save(config_path, data, out_config, url, reload, render_png, snapshot)


@zones.command("remove")
@click.argument("kind", type=click.Choice(["lane", "loop"]))
@click.argument("ident")
@_edit_options
def remove_cmd(kind: str, ident: str, config_path: str, url: str | None, reload: bool, snapshot: str | None,
               render_png: str | None, out_config: str | None) -> None:
    """Remove a lane (by id) or a loop (by id). A lane's loops must be removed first.

    \b
    Example:
      roadwatch zones remove loop L3
    """
    data = read_toml(config_path)
    items = data.get(f"{kind}s", [])
    key = int(ident) if kind == "lane" and ident.isdigit() else ident
    keep = [x for x in items if x.get("id") != key]
    if len(keep) == len(items):
        raise click.ClickException(f"no {kind} with id {ident!r} in {config_path}")
    data[f"{kind}s"] = keep
    _save(config_path, data, out_config, url, reload, render_png, snapshot)


@zones.command("render")
@config_option
@click.option("--snapshot", type=click.Path(exists=True, dir_okay=False),
              help="Snapshot PNG to draw on (default: a frame from the source).")
@click.option("--from-service", is_flag=True, help="Draw on the running service's latest frame.")
@url_option
@click.option("--out", "-o", type=click.Path(dir_okay=False), default="zones.png", show_default=True)
def render_cmd(config_path: str, snapshot: str | None, from_service: bool, url: str | None, out: str) -> None:
    """Draw lanes, zones, loops (with channels) and fiducials over the snapshot.

    \b
    Examples:
      roadwatch zones render --snapshot snap.png -o zones.png
      roadwatch zones render --from-service -o live-zones.png
    """
    cfg = load_config(config_path)
    if from_service:
        import cv2

        from tools.fieldtool.common import service_url
        from tools.fieldtool.statusclient import ServiceError, ServiceUnreachable, StatusClient

        try:
            png = StatusClient(service_url(url, config_path)).snapshot_png(overlay=False)
        except (ServiceError, ServiceUnreachable) as e:
            raise click.ClickException(f"no frame from the service: {e}") from None
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        if img is None or img.shape[:2] != (cfg.source.height, cfg.source.width):
            raise click.ClickException("the service's frame does not match the config's source size")
        write_png(out, draw_site(img, cfg))
    else:
        render(cfg, snapshot, out)
    click.echo(f"wrote {out}")


@zones.command("check")
@config_option
def check_cmd(config_path: str) -> None:
    """Validate the zones (inside the image, loops inside lanes, channels unique) and list them.

    \b
    Example:
      roadwatch zones check -c site.toml
    """
    cfg = load_config(config_path)
    for line in summary(cfg):
        click.echo(line)
    warns = zone_warnings(cfg)
    for w in warns:
        click.echo(f"WARNING: {w}", err=True)
    click.echo("zones ok" + (f" ({len(warns)} warnings)" if warns else ""))
