"""`roadwatch counts-from-sim`: a simulated scene written as a hand-counted clip (../shared/data/README.md format),
so that the real-clip path (site-from-counts, replay of JPEG frames, evaluate --counts, clip-variants) can be
tried on traffic the one real clip lacks: both directions, receding lanes, queues, night, other sizes.

Like a hand count, the file gives only what an installer clicks on a snapshot: lane polygons and one count line
in pixels, calibration points on the lane markings (with click noise if asked), and the frame and lane of every
vehicle whose front crosses the line; the simulator's own site file (fiducials, regions, loops) is not used.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import click
import cv2
import numpy as np

from appliance.config import ConfigError, load_site
from tools.evaluate import truth_crossings
from tools.handcount import HandCountError, count_point, site_dict_from_counts

JPEG_QUALITY = 90


def counts_dict(sim: Path, noise_px: float = 0.0, seed: int = 1, row: float | None = None) -> dict:
    """The hand-count file's content for a simulated scene directory (site.toml, truth/). The count line runs
    across the image at ``row`` (pixels), by default the median row of the simulator's count positions."""
    site = load_site(sim / "site.toml")
    meta = json.loads((sim / "truth" / "meta.json").read_text())
    w, h = int(meta["width"]), int(meta["height"])
    lanes, rows = [], []
    for lane in site.lanes:
        poly = site.homography.road_to_img(np.asarray(lane.polygon_m, dtype=np.float64))
        poly[:, 0] = np.clip(poly[:, 0], 0.0, w - 1.0)
        poly[:, 1] = np.clip(poly[:, 1], 0.0, h - 1.0)
        lanes.append({"id": lane.id, "direction": lane.direction, "polygon_px": np.round(poly, 1).tolist()})
        centre = np.mean(np.asarray(lane.polygon_m, dtype=np.float64)[:, 0])
        rows.append(float(site.homography.road_to_img([[centre, lane.count_y_m]])[0, 1]))
    row = round(float(np.median(rows)) if row is None else float(row), 1)
    if not 0.0 <= row <= h - 1.0:
        raise HandCountError(f"count row {row:g} is outside the {h}-row image")
    line = [[0.0, row], [w - 1.0, row]]
    cal = site.calibration
    rng = np.random.default_rng(seed)
    img = np.asarray(cal.image_px, dtype=np.float64)
    img = img + rng.normal(0.0, noise_px, img.shape) if noise_px > 0 else img
    directions = {ln["direction"] for ln in lanes}
    return {
        "clip": f"{meta.get('preset', 'sim')}-s{meta.get('seed', '')}",
        "file": "input/in%06d.jpg (in000001.jpg = frame 0)",
        "fps": float(meta["fps"]),
        "frames": int(meta["frame_count"]),
        "size": [w, h],
        "direction": directions.pop() if len(directions) == 1 else "both",
        "lanes": lanes,
        "count_line_px": line,
        "count_rule": "the frame in which the vehicle's front (ground contact) is first at or past the line",
        "crossings": [],
        "calibration": {"image_px": np.round(img, 2).tolist(), "road_m": cal.road_m,
                        "basis": f"the simulator's lane markings, click noise {noise_px:g} px"},
        "notes": f"made by roadwatch counts-from-sim from {sim.name}",
    }


def crossings_of(counts: dict, sim: Path) -> list[dict]:
    """Every truth vehicle's front crossing of the count line in each lane, as hand-count crossings: the first
    frame at or after the moment, by the frames' true capture times."""
    with open(sim / "truth" / "frames.csv", newline="") as f:
        times = np.array([float(r["t"]) for r in csv.DictReader(f)])
    site = site_dict_from_counts(counts, sim / "counts.json", sim / "site.toml")
    lines = {int(ln["id"]): float(ln["count_y_m"]) for ln in site["lanes"]}
    out = []
    for c in truth_crossings(sim / "truth" / "vehicles.csv", lines):
        frame = int(np.searchsorted(times, c["t"] - 1e-9))
        if frame < len(times):
            out.append({"frame": frame, "lane": int(c["lane"]), "class": c["class"], "confidence": "exact",
                        "note": f"truth vehicle {c['vehicle_id']}, {c['visible'] * 100:.0f} % visible"})
    return sorted(out, key=lambda c: (c["frame"], c["lane"]))


def write_frames(video: Path, out_dir: Path) -> int:
    """Decode the scene's video into out_dir/input/in000001.jpg...; the number of frames written."""
    (out_dir / "input").mkdir(parents=True, exist_ok=True)
    cap = cv2.VideoCapture(str(video))
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        n += 1
        cv2.imwrite(str(out_dir / "input" / f"in{n:06d}.jpg"), frame, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    cap.release()
    return n


@click.command(name="counts-from-sim")
@click.argument("sim_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Directory for counts.json and input/ (the frames as JPEG).")
@click.option("--click-noise", type=click.FloatRange(min=0), default=0.0, show_default=True, metavar="PX",
              help="Standard deviation of the calibration points' click error (pixels).")
@click.option("--seed", type=int, default=1, show_default=True, help="Seed of the click noise.")
@click.option("--count-row", type=float, default=None, metavar="PX",
              help="Image row of the count line (default: the median row of the simulator's count positions).")
def counts_from_sim(sim_dir: Path, out_dir: Path, click_noise: float, seed: int, count_row: float | None) -> None:
    """Write a simulated scene (roadwatch simulate --out SIM_DIR) as a hand-counted clip.

    \b
    Example:
      roadwatch simulate --preset two-directions --seconds 120 --width 320 --height 240 --out sim
      roadwatch counts-from-sim sim --out clip --click-noise 0.5
      roadwatch site-from-counts clip/counts.json --out clip/site.toml
      roadwatch replay clip/input/in%06d.jpg --config clip/site.toml --fps 25 --out clip/res.sqlite
      roadwatch evaluate --counts clip/counts.json --results clip/res.sqlite
    """
    try:
        counts = counts_dict(sim_dir, click_noise, seed, count_row)
        counts["crossings"] = crossings_of(counts, sim_dir)
    except (ConfigError, FileNotFoundError, KeyError) as e:
        raise click.ClickException(f"{sim_dir}: not a simulated scene roadwatch can read ({e})") from None
    except HandCountError as e:
        raise click.ClickException(f"{sim_dir}: {e}") from None
    out_dir.mkdir(parents=True, exist_ok=True)
    n = write_frames(sim_dir / "video.mp4", out_dir)
    if n != counts["frames"]:
        raise click.ClickException(f"{sim_dir / 'video.mp4'}: {n} frames decoded, the truth has {counts['frames']}")
    (out_dir / "counts.json").write_text(json.dumps(counts, indent=1))
    per_lane = ", ".join(f"lane {ln['id']}: {sum(c['lane'] == ln['id'] for c in counts['crossings'])}"
                         for ln in counts["lanes"])
    click.echo(f"wrote {out_dir / 'counts.json'} ({n} frames in {out_dir / 'input'}): count line at row "
               f"{counts['count_line_px'][0][1]:g}, crossings {per_lane}")
