"""Render a whole scenario to out_dir: video.mp4, site.toml and the truth files (vehicles, loops, periods)."""

from __future__ import annotations

import functools
import json
import math
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from tools.simulate.scene import Scene
from tools.simulate.stream import site_toml
from tools.simulate.truth import AGGREGATE_FIELDS, LOOP_FIELDS, VEHICLE_FIELDS, write_csv


ROW_FORMAT = (
    "{frame},{t:.6f},{vehicle_id},{class},{lane},{x_m:.4f},{y_front_m:.4f},{y_rear_m:.4f},{y_centre_m:.4f},"
    "{speed_mps:.4f},{accel_mps2:.4f},{length_m:.4f},{bbox_x0:.2f},{bbox_y0:.2f},{bbox_x1:.2f},{bbox_y1:.2f},"
    "{visible_frac:.3f}\n"
)
assert ROW_FORMAT.count("{") == len(VEHICLE_FIELDS)


@dataclass
class ScenarioOutput:
    video: Path
    site: Path
    truth_dir: Path
    meta: dict


class VideoWriter:
    """Grey frames to an mp4 file: H.264 through an ffmpeg pipe, or OpenCV's mp4v when ffmpeg is missing.
    gaps: (frame, intervals) where that many frame intervals were left out before that frame (dropped
    frames): its timestamp and the later ones' step over them, as a camera's recording does (ffmpeg only)."""

    def __init__(self, path: Path, width: int, height: int, fps: float, crf: int = 23,
                 gaps: list[tuple[int, int]] | None = None):
        self.path, self.n = path, 0
        self.proc = None
        self.cv = None
        # what the video was encoded with (scenes from the two encoders differ, and so do replays of them)
        self.encoder = f"libx264 crf {crf} (ffmpeg)"
        if shutil.which("ffmpeg"):
            cmd = ["ffmpeg", "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "gray", "-s", f"{width}x{height}",
                   "-r", f"{fps:g}", "-i", "-", *_gap_filter(gaps or [], fps), "-c:v", "libx264",
                   "-preset", "ultrafast", "-tune", "zerolatency", "-crf", str(crf), "-pix_fmt", "yuv420p",
                   "-threads", "1", str(path)]
            self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE)
        else:
            self.encoder = "mp4v (OpenCV; ffmpeg not found: install it for H.264 like a camera's)"
            self.cv = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height), True)
            if not self.cv.isOpened():
                raise RuntimeError(f"cannot open a video writer for {path}")

    def write(self, img: np.ndarray) -> None:
        self.n += 1
        if self.proc is not None:
            self.proc.stdin.write(np.ascontiguousarray(img).tobytes())
        else:
            self.cv.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))

    def close(self) -> None:
        if self.proc is not None:
            self.proc.stdin.close()
            if self.proc.wait() != 0:
                raise RuntimeError(f"ffmpeg failed writing {self.path}")
        else:
            self.cv.release()


def _gap_filter(gaps: list[tuple[int, int]], fps: float) -> list[str]:
    """ffmpeg options giving frame N the timestamp of frame N plus the intervals left out before it."""
    if not gaps:
        return []
    skipped = "+".join(f"{k}*gte(N\\,{n})" for n, k in gaps)  # (a comma ends a filter)
    return ["-vf", f"setpts=(N+{skipped})/({fps!r}*TB)", *_passthrough()]


@functools.cache
def _passthrough() -> list[str]:
    """ffmpeg's option to keep each frame's timestamp (no frames added over the gaps): -fps_mode from 5.1 on,
    -vsync before (it is gone in 9)."""
    out = subprocess.run(["ffmpeg", "-version"], capture_output=True, text=True).stdout
    m = re.match(r"ffmpeg version n?(\d+)\.(\d+)", out)
    old = m is not None and (int(m[1]), int(m[2])) < (5, 1)
    return ["-vsync", "passthrough"] if old else ["-fps_mode", "passthrough"]


def dropped_gaps(dropped: np.ndarray, repeat_frames: int) -> list[tuple[int, int]]:
    """(video frame, intervals left out before it) for each run of dropped captures (each capture is written
    repeat_frames times)."""
    gaps, pending, n = [], 0, 0
    for d in dropped:
        if d:
            pending += repeat_frames
            continue
        if pending:
            gaps.append((n, pending))
            pending = 0
        n += repeat_frames
    return gaps


def capture_times(seconds: float, content_fps: float, jitter_ms: float, rng: np.random.Generator) -> np.ndarray:
    """True capture times of the rendered frames (nominal grid plus jitter, strictly increasing, t0 = 0)."""
    n = max(1, int(math.floor(seconds * content_fps + 1e-9)))
    t = np.arange(n) / content_fps
    if jitter_ms > 0:
        j = rng.normal(0.0, jitter_ms / 1000.0, n)
        j = np.clip(j, -0.3 / content_fps, 0.3 / content_fps)
        j[0] = 0.0
        t = t + j
    return t


def render_scenario(preset: str, seed: int, seconds: float, out_dir: Path, *, width: int = 640, height: int = 480,
                    fps: float = 25.0, progress: bool = False, png_every_s: float = 0.0,
                    **overrides: object) -> "ScenarioOutput":
    """Render `seconds` of a preset scene with its exact truth into out_dir (created if missing).

    png_every_s > 0 also saves out_dir/frames/frame_NNNNNN.png every that many seconds (for looking at).
    """
    if seconds <= 0:
        raise ValueError(f"seconds must be positive, got {seconds}")
    out_dir = Path(out_dir)
    scene = Scene(preset, seed, width=width, height=height, fps=fps, **overrides)
    truth_dir = out_dir / "truth"
    truth_dir.mkdir(parents=True, exist_ok=True)
    p = scene.p
    rng = np.random.default_rng([int(seed), 7])
    content_fps = fps / p.repeat_frames
    times = capture_times(seconds, content_fps, p.jitter_ms, rng)
    dropped = (rng.random(len(times)) < p.drop_prob) & (np.arange(len(times)) > 0)

    site = scene.site_dict("video.mp4")
    site["source"]["realtime"] = False
    if p.interlaced:
        site["source"]["deinterlace"] = True
    site_path = out_dir / "site.toml"
    site_path.write_text(site_toml(site))

    video_path = out_dir / "video.mp4"
    writer = VideoWriter(video_path, width, height, fps, p.video_crf, dropped_gaps(dropped, p.repeat_frames))
    frames_rows = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(times), unit="frame", desc=f"{preset} seed {seed}")
    vf = open(truth_dir / "vehicles.csv", "w", newline="")
    vf.write(",".join(VEHICLE_FIELDS) + "\n")
    t_prev = 0.0
    next_png = 0.0
    drop_pending = False
    try:
        for i, t in enumerate(times):
            if t > t_prev:
                scene.step(float(t - t_prev))
                t_prev = float(t)
            if dropped[i]:
                drop_pending = True
                if bar:
                    bar.update(1)
                continue
            img, rows = scene.render()
            if p.interlaced:  # the bottom field, half a frame later (the truth is the top field's time)
                half = 0.5 / content_fps
                scene.step(half)
                t_prev = float(t) + half
                img = img.copy()
                img[1::2] = scene.render(want_truth=False)[0][1::2]
            frame = writer.n
            if png_every_s > 0 and t >= next_png:
                (out_dir / "frames").mkdir(exist_ok=True)
                cv2.imwrite(str(out_dir / "frames" / f"frame_{frame:06d}.png"), img)
                next_png += png_every_s
            for r in range(p.repeat_frames):
                frames_rows.append(dict(frame=writer.n, t=round(float(t), 6), repeated=r > 0,
                                        dropped_before=drop_pending and r == 0))
                writer.write(img)
            drop_pending = False
            for row in rows:
                vf.write(ROW_FORMAT.format(frame=frame, t=float(t), **row))
            if bar:
                bar.update(1)
        # the truth runs to the end of the scenario even when the last frames were dropped or padded
        t_end = len(times) / content_fps
        if t_end > t_prev:
            scene.step(t_end - t_prev)
    finally:
        vf.close()
        writer.close()
        if bar:
            bar.close()

    write_csv(truth_dir / "loop_events.csv", LOOP_FIELDS, scene.truth.loop_events)
    write_csv(truth_dir / "aggregates.csv", AGGREGATE_FIELDS, scene.truth.aggregates())
    write_csv(truth_dir / "frames.csv", ["frame", "t", "repeated", "dropped_before"], frames_rows)
    meta = dict(
        preset=preset, seed=int(seed), fps=float(fps), width=width, height=height, seconds=float(seconds),
        frame_count=writer.n, encoder=writer.encoder, start_wall=scene.truth.start_wall, period_s=scene.truth.period_s,
        defects=dict(repeat_frames=p.repeat_frames, drop_prob=p.drop_prob, jitter_ms=p.jitter_ms,
                     dropped_frames=int(dropped.sum()), interlaced=p.interlaced),
        camera=dict(height_m=scene.cam.height_m, tilt_deg=scene.cam.tilt_deg, pan_deg=scene.cam.pan_deg,
                    focal_px=scene.cam.focal_px, x_m=scene.cam.x_m),
        conditions={k: getattr(p, k) for k in ("night", "dusk", "rain", "overcast", "shadows", "shake_px",
                                               "drift_px_per_min", "noise_sigma", "defocus")},
        overrides={k: v for k, v in overrides.items() if v is not None},
        frames_file="truth/frames.csv",
        vehicles_spawned=int(scene.traffic.next_id - 1),
    )
    if p.curve_radius_m:
        meta["road"] = dict(curve_radius_m=p.curve_radius_m, centre_x="Y^2 / (2 R)",
                            speeds="along Y (dY/dt), the frame of the counts, loops and Edie quantities")
    (truth_dir / "meta.json").write_text(json.dumps(meta, indent=1))
    return ScenarioOutput(video_path, site_path, truth_dir, meta)
