"""`roadwatch bench`: frames per second per core of each vision stage and the whole pipeline, next to decoding."""

# Scenes come from the simulator (rendered once, cached in the temp directory); the process is pinned to one core.

from __future__ import annotations

import csv
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import click
import cv2

from appliance.config import load_site
from appliance.pipeline import VisionPipeline
from appliance.types import Frame

SIZES = {"640x480": (640, 480), "1280x720": (1280, 720)}
PRESETS = ("free-flow", "dense")
STAGES = ("stabilise", "detect", "track", "group", "presence")


def scene_dir(preset: str, size: str, seconds: float, seed: int) -> Path:
    """Render the scene once into the temp directory and return its folder."""
    w, h = SIZES[size]
    d = Path(tempfile.gettempdir()) / "roadwatch-bench" / f"{preset}-s{seed}-{size}-{seconds:g}s"
    if not (d / "video.mp4").is_file() or not (d / "truth" / "meta.json").is_file():
        click.echo(f"rendering {preset} {size} {seconds:g} s (once, cached in {d}) ...", err=True)
        # by `roadwatch simulate`, in a process of its own: the renderer's memory is not the pipeline's peak RSS
        r = subprocess.run([sys.executable, "-m", "tools.cli", "simulate", "--preset", preset, "--seed", str(seed),
                            "--seconds", repr(seconds), "--out", str(d), "--width", str(w), "--height", str(h),
                            "--fps", "25", "--quiet"], capture_output=True, text=True)
        if r.returncode != 0:
            raise click.ClickException(f"rendering {preset} {size} failed: {r.stderr.strip()[-500:]}")
    return d


def _frames(d: Path):
    times = [float(r["t"]) for r in csv.DictReader(open(d / "truth" / "frames.csv"))]
    cap = cv2.VideoCapture(str(d / "video.mp4"))
    if not cap.isOpened():
        raise click.ClickException(f"{d / 'video.mp4'}: cannot be opened")
    k = 0
    try:
        while k < len(times):
            ok, img = cap.read()
            if not ok:
                break
            yield k, times[k], img
            k += 1
    finally:
        cap.release()


def decode_fps(d: Path) -> float:
    """Frames per second of decoding the video to grey (what a frame source does per frame)."""
    t0 = time.perf_counter()
    n = 0
    for _, _, img in _frames(d):
        cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        n += 1
    return n / max(time.perf_counter() - t0, 1e-9)


def pipeline_run(d: Path) -> dict:
    """Run the pipeline over the scene; only the pipeline's own time is counted."""
    site = load_site(d / "site.toml")
    pipe = VisionPipeline(site)
    pipe.warmup()
    busy = 0.0
    n = 0
    feats = 0
    for k, t, img in _frames(d):
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        c0 = time.perf_counter()
        pipe.step(Frame(seq=k, t=t, wall=1767225600.0 + t, image=grey))
        busy += time.perf_counter() - c0
        n += 1
        feats += pipe.stats["features"]
    out = {"frames": n, "pipeline_fps": n / max(busy, 1e-9), "mean_features": feats / max(n, 1),
           "vehicles_finished": pipe.stats["finished"]}
    for s in STAGES:
        out[f"{s}_fps"] = n / max(pipe.timings[s], 1e-9)
    return out


def cold_warmup_s() -> float:
    """Numba compile time of all kernels in a fresh process with an empty cache."""
    code = (
        "import time;from appliance.pipeline import VisionPipeline;"
        "import tools.simulate.stream as s;from appliance.config import parse_site;"
        "p=VisionPipeline(parse_site(s.site_config_dict('free-flow')));t=time.perf_counter();p.warmup();"
        "print(time.perf_counter()-t)"
    )
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
        if r.returncode != 0:
            raise click.ClickException(f"warm-up subprocess failed: {r.stderr.strip()[-500:]}")
        return float(r.stdout.strip().splitlines()[-1])


def warm_warmup_s() -> float:
    """Load time of the cached kernels in a fresh process (what the service pays at start)."""
    code = (
        "import time;from appliance.pipeline import VisionPipeline;"
        "import tools.simulate.stream as s;from appliance.config import parse_site;"
        "p=VisionPipeline(parse_site(s.site_config_dict('free-flow')));t=time.perf_counter();p.warmup();"
        "print(time.perf_counter()-t)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    if r.returncode != 0:
        raise click.ClickException(f"warm-up subprocess failed: {r.stderr.strip()[-500:]}")
    return float(r.stdout.strip().splitlines()[-1])


@click.command(name="bench", help="Measure frames per second per core and memory.")
@click.option("--seconds", default=20.0, show_default=True, help="Length of each rendered scene.")
@click.option("--seed", default=1, show_default=True)
@click.option("--core", type=int, default=None, help="CPU core to pin to (default: the last allowed one).")
@click.option("--size", "sizes", multiple=True, type=click.Choice(list(SIZES)), help="Frame sizes (default both).")
@click.option("--preset", "presets", multiple=True, type=click.Choice(list(PRESETS)), help="Scenes (default both).")
@click.option("--json", "json_out", type=click.Path(dir_okay=False), default=None, help="Also write results as JSON.")
@click.option("--no-compile", is_flag=True, help="Skip the cold numba compile measurement.")
def bench(seconds: float, seed: int, core: int | None, sizes: tuple[str, ...], presets: tuple[str, ...],
          json_out: str | None, no_compile: bool) -> None:
    if seconds <= 0:
        raise click.BadParameter("must be positive", param_hint="--seconds")
    allowed = sorted(os.sched_getaffinity(0))
    core = allowed[-1] if core is None else core
    if core not in allowed:
        raise click.BadParameter(f"core {core} is not available (allowed: {allowed})", param_hint="--core")
    sizes = sizes or tuple(SIZES)
    presets = presets or PRESETS
    dirs = {(p, s): scene_dir(p, s, seconds, seed) for p in presets for s in sizes}
    os.sched_setaffinity(0, {core})
    result: dict = {"core": core, "seconds": seconds, "seed": seed, "runs": []}
    if not no_compile:
        result["numba_compile_s"] = round(cold_warmup_s(), 2)
    result["numba_cached_load_s"] = round(warm_warmup_s(), 2)
    for (p, s), d in dirs.items():
        dec = decode_fps(d)
        run = pipeline_run(d)
        run.update(preset=p, size=s, decode_fps=dec, cost_vs_decode=dec / run["pipeline_fps"])
        result["runs"].append(run)
    result["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)

    head = ["scene", "size", "decode", "pipeline", "x decode", *STAGES, "features", "vehicles"]
    rows = [
        [r["preset"], r["size"], f"{r['decode_fps']:.0f}", f"{r['pipeline_fps']:.0f}", f"{r['cost_vs_decode']:.2f}",
         *[f"{r[f'{s}_fps']:.0f}" for s in STAGES], f"{r['mean_features']:.0f}", str(r["vehicles_finished"])]
        for r in result["runs"]
    ]
    widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(head)]
    click.echo(f"frames per second on core {core} ({seconds:g} s scenes, seed {seed}); stage columns are fps of that stage alone")
    click.echo("  ".join(h.rjust(w) for h, w in zip(head, widths)))
    for row in rows:
        click.echo("  ".join(c.rjust(w) for c, w in zip(row, widths)))
    if "numba_compile_s" in result:
        click.echo(f"numba compile (cold cache): {result['numba_compile_s']:.1f} s")
    click.echo(f"numba kernels from cache at start: {result['numba_cached_load_s']:.1f} s")
    click.echo(f"peak RSS: {result['peak_rss_mb']:.0f} MB")
    if json_out:
        Path(json_out).write_text(json.dumps(result, indent=1))
