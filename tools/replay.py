"""`roadwatch replay`: run the vision pipeline and the traffic measures on a video or image sequence."""

from __future__ import annotations

import csv
import json
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import click
import cv2
import numpy as np

from appliance.config import ConfigError, SiteConfig, load_site
from appliance.measures import TrafficMeasures
from appliance.types import Frame, LaneAggregate, LoopEvent, VehicleRecord
from drivers.sources import FileClock

DEFAULT_START_WALL = 1767225600.0  # 2026-01-01T00:00:00Z, the simulator's epoch


class ReplayError(RuntimeError):
    """The video cannot be replayed (names the file and the problem)."""


@dataclass
class ReplayResult:
    periods: list[LaneAggregate] = field(default_factory=list)
    loop_events: list[LoopEvent] = field(default_factory=list)
    vehicles: list[VehicleRecord] = field(default_factory=list)
    frames: int = 0
    crossings: list[dict] = field(default_factory=list)  # Crossing fields + "frame" (seq where seen)
    fps: float = 0.0
    truncated: str | None = None  # why reading stopped early, when it did
    seconds: float = 0.0  # processing wall time
    # the Edie segments added (+1) and taken back (-1), when asked: (vehicle, lane, w0, w1, y0, y1, sign, x)
    edie_segments: list[tuple] = field(default_factory=list)


def parse_start(text: str | None) -> float:
    """ISO 8601 time (``Z`` or offset; naive = UTC) -> Unix seconds."""
    if not text:
        return DEFAULT_START_WALL
    try:
        dt = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise click.BadParameter(f"{text!r} is not an ISO 8601 time (e.g. 2026-01-01T00:00:00Z)") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.timestamp()


def is_image_sequence(video: str) -> bool:
    return "%" in Path(video).name


class VideoFrames:
    """Frames of a video file or image sequence with capture times (see FileClock)."""

    def __init__(self, video: str, fps: float | None, start_wall: float, site: SiteConfig | None = None):
        self.video = str(video)
        if not is_image_sequence(self.video) and not Path(self.video).exists():
            raise ReplayError(f"{self.video}: no such file")
        self.cap = cv2.VideoCapture(self.video)
        if not self.cap.isOpened():
            raise ReplayError(f"{self.video}: cannot be opened as a video or image sequence")
        self.sequence = is_image_sequence(self.video)
        native = self.cap.get(cv2.CAP_PROP_FPS)
        if fps is not None:
            self.fps = float(fps)
        elif not self.sequence and native and 0 < native <= 240:
            self.fps = float(native)
        elif site is not None and site.source.fps:
            self.fps = float(site.source.fps)  # image sequences carry no rate: the config's
        else:
            raise ReplayError(f"{self.video}: the frame rate is unknown; give --fps")
        self.expected = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        self.start_wall = start_wall
        self.seq = 0
        # a given --fps overrides the container's clock
        self.clock = FileClock(self.fps, use_container=fps is None and not self.sequence)
        self.site = site

    def read(self) -> tuple[Frame, np.ndarray] | None:
        ok, img = self.cap.read()
        if not ok or img is None:
            return None
        if self.seq == 0 and self.site is not None:
            h, w = img.shape[:2]
            if (w, h) != (self.site.source.width, self.site.source.height):
                raise ReplayError(
                    f"{self.video}: frames are {w}x{h} but the config (source.width x source.height) is "
                    f"{self.site.source.width}x{self.site.source.height}"
                )
        t = self.clock.next(self.cap)
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
        frame = Frame(seq=self.seq, t=t, wall=self.start_wall + t, image=np.ascontiguousarray(grey))
        self.seq += 1
        return frame, img

    def truncation(self) -> str | None:
        if self.expected > 0 and self.seq < self.expected - 1 and not self.sequence:
            return f"{self.video}: the video ended after {self.seq} of {self.expected} frames (truncated or damaged)"
        return None

    def close(self) -> None:
        self.cap.release()


def replay_video(
    video: str,
    site: SiteConfig,
    fps: float | None = None,
    start_wall: float = DEFAULT_START_WALL,
    annotate: str | None = None,
    snapshots: str | None = None,
    snapshot_every: int = 50,
    progress: bool = False,
    max_frames: int | None = None,
    pipeline_factory: Callable | None = None,
    trajectories: bool = True,
    edie_log: bool = False,
) -> ReplayResult:
    """Run VisionPipeline + TrafficMeasures over a video; results include the partial last period (and with
    edie_log every Edie segment the measures added or took back)."""
    if pipeline_factory is None:
        from appliance.pipeline import VisionPipeline

        pipeline_factory = VisionPipeline
    frames = VideoFrames(video, fps, start_wall, site)
    pipe = pipeline_factory(site)
    if hasattr(pipe, "warmup"):
        pipe.warmup()
    measures = TrafficMeasures(site)
    measures.keep_trajectories = trajectories  # bounded per vehicle; for time-space diagrams
    res = ReplayResult(fps=frames.fps)
    if edie_log:
        measures.edie_log = res.edie_segments
    writer = None
    if snapshots:
        Path(snapshots).mkdir(parents=True, exist_ok=True)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=frames.expected or None, unit="frame", desc=Path(video).name, leave=False)
    t0 = time.perf_counter()
    last: Frame | None = None
    try:
        while max_frames is None or res.frames < max_frames:
            got = frames.read()
            if got is None:
                break
            frame, colour = got
            try:
                states = pipe.step(frame)
            except ValueError as e:  # a frame the pipeline cannot take (e.g. the size changed mid-stream)
                raise ReplayError(f"{video}: {e}") from None
            upd = measures.step(frame.t, frame.wall, states, getattr(pipe, "loop_sights", None))
            res.periods += upd.periods
            res.loop_events += upd.loop_events
            res.vehicles += upd.vehicles
            res.crossings += [dict(c.to_dict(), frame=frame.seq) for c in upd.crossings]
            if annotate or (snapshots and frame.seq % snapshot_every == 0):
                img = pipe.overlay(colour) if hasattr(pipe, "overlay") else colour
                if annotate:
                    if writer is None:
                        h, w = img.shape[:2]
                        writer = cv2.VideoWriter(annotate, cv2.VideoWriter_fourcc(*"mp4v"), frames.fps, (w, h))
                        if not writer.isOpened():
                            raise ReplayError(f"{annotate}: cannot write the annotated video")
                    writer.write(img)
                if snapshots and frame.seq % snapshot_every == 0:
                    cv2.imwrite(str(Path(snapshots) / f"frame{frame.seq:06d}.png"), img)
            res.frames += 1
            last = frame
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.release()
        frames.close()
    if res.frames == 0:
        raise ReplayError(f"{video}: contains no decodable frame")
    res.truncated = frames.truncation() if max_frames is None else None
    res.periods += measures.flush(last.wall + 1.0 / frames.fps)  # the last frame stands for one interval
    res.seconds = time.perf_counter() - t0
    return res


# ------------------------------------------------------------------------------------ output

CROSSING_COLUMNS = ["vehicle_id", "lane", "frame", "t", "wall", "speed_kmh", "length_m", "y"]
EDIE_COLUMNS = ["vehicle_id", "lane", "w0", "w1", "y0", "y1", "sign", "x"]


def write_results(res: ReplayResult, out: str, vehicles: bool) -> list[str]:
    """Write periods, crossings and loop events (and vehicles when asked) to .sqlite or .csv files."""
    p = Path(out)
    written = []
    if p.suffix.lower() == ".csv":
        def dump(path: Path, rows: list[dict]) -> None:
            if not rows:
                path.write_text("")
                return
            with path.open("w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(rows[0]))
                w.writeheader()
                for r in rows:
                    w.writerow({k: (json.dumps(v) if isinstance(v, (dict, list)) else v) for k, v in r.items()})
            written.append(str(path))

        dump(p, [a.to_dict() for a in res.periods])
        dump(p.with_name(p.stem + "_crossings.csv"), [{c: r[c] for c in CROSSING_COLUMNS} for r in res.crossings])
        # loop events are the emulated detectors' output: always written (evaluate compares them)
        dump(p.with_name(p.stem + "_loop_events.csv"), [e.to_dict() for e in res.loop_events])
        if vehicles:
            dump(p.with_name(p.stem + "_vehicles.csv"), [r.to_dict() for r in res.vehicles])
            dump(p.with_name(p.stem + "_edie_segments.csv"), [dict(zip(EDIE_COLUMNS, sg)) for sg in res.edie_segments])
        return written
    from appliance.store import Store

    store = Store(p)
    try:
        store.write_periods(res.periods)
        tbl = store.db["crossings"]
        if tbl.exists():
            tbl.delete_where()
        tbl.insert_all([{c: r[c] for c in CROSSING_COLUMNS} for r in res.crossings],
                       columns={c: (int if c in ("vehicle_id", "lane", "frame") else float) for c in CROSSING_COLUMNS})
        store.write_loop_events(res.loop_events)
        if vehicles:
            store.write_vehicles(res.vehicles, trajectories=True)
            tbl = store.db["edie_segments"]
            if tbl.exists():
                tbl.delete_where()
            tbl.insert_all((dict(zip(EDIE_COLUMNS, sg)) for sg in res.edie_segments), batch_size=5000,
                           columns={c: (int if c in ("vehicle_id", "lane") else float) for c in EDIE_COLUMNS})
    finally:
        store.close()
    return [str(p)]


def format_table(periods: list[LaneAggregate]) -> str:
    def f(x, fmt="{:.1f}"):
        return "-" if x is None else fmt.format(x)

    head = f"{'period start (UTC)':<20} {'lane':>4} {'count':>5} {'q veh/h':>8} {'k veh/km':>8} {'v km/h':>7} " \
           f"{'tms km/h':>8} {'v85':>6} {'occ %':>6} {'hdwy s':>6}  flags"
    lines = [head, "-" * len(head)]
    for a in sorted(periods, key=lambda a: (a.period_start, a.lane)):
        start = datetime.fromtimestamp(a.period_start, timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
        lines.append(
            f"{start:<20} {a.lane:>4} {a.count:>5} {a.flow_vph:>8.0f} {a.density_vpkm:>8.1f} {f(a.speed_kmh):>7} "
            f"{f(a.time_mean_speed_kmh):>8} {f(a.speed85_kmh):>6} {f(a.occupancy_pct):>6} {f(a.headway_s):>6}  "
            f"{'partial' if a.partial else ''}"
        )
    return "\n".join(lines)


def source_video(site: SiteConfig) -> str:
    """The site's own file or image-sequence source (relative paths are relative to the site file)."""
    url = site.source.url
    if url.startswith(("synthetic:", "rtsp://", "http://", "https://", "/dev/")):
        raise click.UsageError(f"the config's source ({url}) is not a file; give VIDEO")
    rel = url.removeprefix("images:")
    p = Path(rel)
    if not p.is_absolute() and site.path:
        p = Path(site.path).resolve().parent / p
    return str(p)


@click.command(name="replay")
@click.argument("video", required=False)
@click.option("--config", "config_path", required=True, type=click.Path(dir_okay=False), help="Site TOML.")
@click.option("--fps", type=float, default=None, help="Frame rate; overrides the file's clock. Image sequences carry none: default source.fps.")
@click.option("--out", type=click.Path(dir_okay=False), default=None, help="results.sqlite or results.csv")
@click.option("--vehicles", is_flag=True,
              help="Also write per-vehicle records (with trajectories) and the Edie segments counted.")
@click.option("--annotate", type=click.Path(dir_okay=False), default=None, help="Write an annotated video (mp4).")
@click.option("--snapshots", type=click.Path(file_okay=False), default=None, help="Write annotated PNGs here.")
@click.option("--start", default=None, help="Wall time of the first frame, ISO 8601 (default 2026-01-01T00:00:00Z).")
@click.option("--max-frames", type=int, default=None, help="Stop after this many frames.")
@click.option("--truth-tracks", type=click.Path(file_okay=False), default=None,
              help="Instead of a video: the simulator truth DIR's exact trajectories (a perfect tracker), "
                   "to separate measurement from tracking errors.")
def replay(video: str | None, config_path: str, fps: float | None, out: str | None, vehicles: bool,
           annotate: str | None, snapshots: str | None, start: str | None, max_frames: int | None,
           truth_tracks: str | None) -> None:
    """Run the pipeline on VIDEO (a file, or an image pattern like input/in%06d.jpg) as fast as it can.

    Without VIDEO the config's own file source is used (e.g. a site made by site-from-counts).
    """
    if annotate and snapshots:
        raise click.UsageError("give --annotate or --snapshots, not both")
    try:
        site = load_site(config_path)
    except ConfigError as e:
        raise click.ClickException(f"config: {e}") from None
    if truth_tracks:
        if not (Path(truth_tracks) / "vehicles.csv").exists():
            raise click.BadParameter(f"{truth_tracks} has no vehicles.csv", param_hint="--truth-tracks")
        t0 = time.perf_counter()
        res = replay_truth_tracks(truth_tracks, site, parse_start(start) if start else None)
        res.seconds = time.perf_counter() - t0
    else:
        if video is None:
            video = source_video(site)
        if fps is not None and fps <= 0:
            raise click.BadParameter("must be positive", param_hint="--fps")
        try:
            res = replay_video(video, site, fps=fps, start_wall=parse_start(start), annotate=annotate,
                               snapshots=snapshots, progress=True, max_frames=max_frames, edie_log=vehicles)
        except ReplayError as e:
            raise click.ClickException(str(e)) from None
    if res.truncated:
        click.echo(f"warning: {res.truncated}; results cover the frames read", err=True)
    click.echo(format_table(res.periods))
    lanes = sorted({a.lane for a in res.periods})
    counts = ", ".join(f"lane {ln}: {sum(1 for c in res.crossings if c['lane'] == ln)}" for ln in lanes)
    click.echo(f"\n{res.frames} frames in {res.seconds:.1f} s ({res.frames / max(res.seconds, 1e-9):.0f} frames/s); "
               f"crossings {counts}; {len(res.vehicles)} vehicles finished; {len(res.loop_events)} loop events")
    if out:
        for path in write_results(res, out, vehicles):
            click.echo(f"wrote {path}")


# ------------------------------------------------------------------------------------ perfect tracker


def truth_vehicle_frames(vehicles_csv: str | Path, site: SiteConfig) -> list[tuple[float, list]]:
    """The simulator's exact trajectories as the tracker would report them: per frame (t, states),
    each vehicle provisional until its last row, which is marked finished."""
    from appliance.types import VehicleState

    sign = {lane.id: (-1.0 if lane.direction == "approaching" else 1.0) for lane in site.lanes}
    rows: list[tuple] = []
    last_row: dict[int, int] = {}
    with open(vehicles_csv, newline="") as f:
        for i, r in enumerate(csv.DictReader(f)):
            vid = int(r["vehicle_id"])
            yf, yr = float(r["y_front_m"]), float(r["y_rear_m"])
            s = sign.get(int(r["lane"]), -1.0 if yr > yf else 1.0)
            rows.append((int(r["frame"]), float(r["t"]), vid, float(r["x_m"]), yf, yr,
                         s * float(r["speed_mps"]), float(r["length_m"])))
            last_row[vid] = i
    frames: dict[int, tuple[float, list]] = {}
    for i, (fr, t, vid, x, yf, yr, vy, length) in enumerate(rows):
        entry = frames.setdefault(fr, (t, []))
        entry[1].append(VehicleState(vid, t, x, yf, yr, 0.0, vy, length, 1, finished=last_row[vid] == i))
    return [frames[k] for k in sorted(frames)]


def replay_truth_tracks(truth_dir: str | Path, site: SiteConfig, start_wall: float | None = None) -> ReplayResult:
    """TrafficMeasures fed with the simulator's exact trajectories (a perfect tracker)."""
    d = Path(truth_dir)
    meta = json.loads((d / "meta.json").read_text()) if (d / "meta.json").exists() else {}
    if start_wall is None:
        start_wall = float(meta.get("start_wall", DEFAULT_START_WALL))
    by_frame = dict((round(t, 6), states) for t, states in truth_vehicle_frames(d / "vehicles.csv", site))
    times = sorted(by_frame)
    if (d / "frames.csv").exists():  # every frame, also those without a vehicle in view
        with open(d / "frames.csv", newline="") as f:
            times = sorted({round(float(r["t"]), 6) for r in csv.DictReader(f)} | set(times))
    measures = TrafficMeasures(site)
    res = ReplayResult(fps=float(meta.get("fps", 0.0)))
    measures.edie_log = res.edie_segments
    last_wall = start_wall
    for seq, t in enumerate(times):
        states = by_frame.get(t, [])
        upd = measures.step(t, start_wall + t, states)
        res.periods += upd.periods
        res.loop_events += upd.loop_events
        res.vehicles += upd.vehicles
        res.crossings += [dict(c.to_dict(), frame=seq) for c in upd.crossings]
        res.frames += 1
        last_wall = start_wall + t
    end = start_wall + float(meta["seconds"]) if "seconds" in meta else last_wall
    res.periods += measures.flush(max(end, last_wall))
    return res
