"""`roadwatch simulate`: render a synthetic traffic scene with its exact ground truth."""

from __future__ import annotations

import time
from pathlib import Path

import click

from tools.simulate.presets import PRESETS


def _preset_help() -> str:
    return "\n".join(f"  {name:<17} {text}" for name, text in PRESETS.items())


@click.command(
    "simulate",
    help=(
        "Render a synthetic traffic scene with exact ground truth.\n\n"
        "Writes OUT/video.mp4, OUT/site.toml (a site config the service and replay read as is) and\n"
        "OUT/truth/ (vehicles.csv per frame and vehicle, loop_events.csv, aggregates.csv per lane and\n"
        "5-minute period, frames.csv with true capture times, meta.json).\n\n"
        "\b\nPresets:\n" + _preset_help() + "\n\n"
        "\b\nExample:\n  roadwatch simulate --preset dense --seconds 300 --out dense"
    ),
)
@click.option("--preset", "-p", type=click.Choice(list(PRESETS)), default="free-flow", show_default=True)
@click.option("--seed", type=int, default=1, show_default=True, help="Same seed, same scene.")
@click.option("--seconds", type=click.FloatRange(min=0.04), default=60.0, show_default=True)
@click.option("--out", "-o", type=click.Path(file_okay=False, path_type=Path), required=True, help="Output directory.")
@click.option("--width", type=click.IntRange(min=64), default=640, show_default=True)
@click.option("--height", type=click.IntRange(min=48), default=480, show_default=True)
@click.option("--fps", type=click.FloatRange(min=1, max=240), default=25.0, show_default=True)
@click.option("--lanes", type=click.IntRange(1, 6), default=None, help="Approaching lanes (overrides the preset).")
@click.option("--receding-lanes", type=click.IntRange(0, 5), default=None, help="Receding lanes.")
@click.option("--curve-radius", type=float, default=None, metavar="METRES",
              help="Bend the road: radius in m (+ right, - left, 0 straight; |R| >= 200).")
@click.option("--demand", type=click.FloatRange(min=0), default=None, help="Demand per lane (veh/h).")
@click.option("--demand-profile", default=None, metavar="T:F,...",
              help="Demand factor over time, piecewise linear, e.g. '0:0.5,600:1.5,1200:0.8'.")
@click.option("--cam-height", type=click.FloatRange(min=3, max=40), default=None, help="Camera height (m).")
@click.option("--tilt", type=click.FloatRange(min=3, max=80), default=None, help="Camera tilt down (degrees).")
@click.option("--pan", type=float, default=None, help="Camera pan (degrees, + right); default aims at the road.")
@click.option("--focal", type=click.FloatRange(min=0.3, max=5), default=None,
              help="Focal length as a multiple of the image width (1.1 = about 49 degrees across).")
@click.option("--repeat-frames", type=click.IntRange(1, 4), default=None, help="Write each frame N times (15 fps padded to 30 = 2).")
@click.option("--drop-frames", type=click.FloatRange(0, 0.5), default=None, help="Probability of dropping a frame.")
@click.option("--jitter-ms", type=click.FloatRange(min=0), default=None, help="Capture timestamp jitter (ms, s.d.).")
@click.option("--interlace", is_flag=True, default=None,
              help="Interlaced frames: odd lines taken half a frame after even lines (site gets deinterlace).")
@click.option("--crf", type=click.IntRange(0, 51), default=None, help="H.264 quality (higher = more compression).")
@click.option("--png-every", type=click.FloatRange(min=0), default=0.0, metavar="SECONDS",
              help="Also save a PNG frame every SECONDS to OUT/frames/ (0 = none).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def simulate(preset: str, seed: int, seconds: float, out: Path, width: int, height: int, fps: float, lanes: int | None,
             receding_lanes: int | None, curve_radius: float | None, demand: float | None, demand_profile: str | None,
             cam_height: float | None, tilt: float | None, pan: float | None, focal: float | None,
             repeat_frames: int | None, drop_frames: float | None, jitter_ms: float | None, interlace: bool | None,
             crf: int | None, png_every: float, quiet: bool) -> None:
    from tools.simulate.scenario import render_scenario

    profile = None
    if demand_profile:
        try:
            profile = [[float(a), float(b)] for a, b in (item.split(":") for item in demand_profile.split(","))]
        except ValueError:
            raise click.BadParameter(f"expected T:F pairs separated by commas, got {demand_profile!r}",
                                     param_hint="--demand-profile") from None
        if any(b < 0 for _, b in profile) or [a for a, _ in profile] != sorted(a for a, _ in profile):
            raise click.BadParameter("times must increase and factors be >= 0", param_hint="--demand-profile")

    overrides = dict(lanes_approaching=lanes, lanes_receding=receding_lanes, curve_radius_m=curve_radius,
                     demand_vph=demand, cam_height_m=cam_height, cam_tilt_deg=tilt, cam_pan_deg=pan, focal_scale=focal,
                     repeat_frames=repeat_frames,
                     drop_prob=drop_frames, jitter_ms=jitter_ms, interlaced=interlace or None, demand_profile=profile,
                     video_crf=crf)
    t0 = time.perf_counter()
    try:
        res = render_scenario(preset, seed, seconds, out, width=width, height=height, fps=fps,
                              progress=not quiet, png_every_s=png_every, **overrides)
    except ValueError as e:
        raise click.BadParameter(str(e)) from None
    dt = time.perf_counter() - t0
    n = res.meta["frame_count"]
    click.echo(f"wrote {res.video} ({n} frames, {width}x{height} @ {fps:g} fps, {res.meta['encoder']}), {res.site}, "
               f"{res.truth_dir}/")
    click.echo(f"rendered in {dt:.1f} s: {n / dt:.0f} frames/s")
