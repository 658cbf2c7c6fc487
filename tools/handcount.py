"""Hand-count files (../shared/data/README.md format): read them, and `roadwatch site-from-counts`."""

from __future__ import annotations

import json
import os
from pathlib import Path

import click
import cv2
import numpy as np

from appliance.config import ConfigError, parse_site
from appliance.geometry import Homography


class HandCountError(ValueError):
    """The hand-count file is missing something or malformed (names the key)."""


def load_counts(path: str | Path) -> dict:
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise HandCountError(f"{p}: no such file") from None
    except json.JSONDecodeError as e:
        raise HandCountError(f"{p}: not valid JSON ({e})") from None
    for key in ("size", "lanes", "count_line_px", "crossings", "calibration"):
        if key not in data:
            raise HandCountError(f"{p}: missing key '{key}'")
    for i, c in enumerate(data["crossings"]):
        if "frame" not in c or "lane" not in c:
            raise HandCountError(f"{p}: crossings[{i}] needs 'frame' and 'lane'")
    return data


def sequence_pattern(counts: dict) -> str | None:
    """The image-sequence pattern named by the ``file`` key (first word), if any."""
    f = counts.get("file")
    return f.split()[0] if isinstance(f, str) and f.strip() else None


def site_dict_from_counts(counts: dict, counts_path: str | Path, out_path: str | Path) -> dict:
    """A site-config dict for the clip: calibration, lanes, count line, loops, source."""
    cal = counts["calibration"]
    try:
        H = Homography.from_points(cal["image_px"], cal["road_m"])
    except (KeyError, ValueError) as e:
        raise HandCountError(f"calibration: {e}") from None
    width, height = (int(v) for v in counts["size"])
    lanes = []
    for i, ln in enumerate(counts["lanes"]):
        poly = np.asarray(ln["polygon_px"], dtype=np.float64)
        where = count_point(poly, counts["count_line_px"])
        if where is None:
            raise HandCountError(f"lanes[{i}]: the count line {counts['count_line_px']} does not cross this lane")
        xc, yc = where
        count_y = float(H.img_to_road([[xc, yc]])[0, 1])
        lanes.append({
            "id": int(ln["id"]),
            "direction": ln.get("direction", counts.get("direction", "approaching")),
            "polygon_px": poly.tolist(),
            "count_y_m": round(count_y, 3),
        })
    loops = []
    occ = counts.get("loop_occupancy") or {}
    for zone in occ.get("lanes", []):
        loops.append({"id": f"L{zone['lane']}", "lane": int(zone["lane"]), "channel": int(zone["lane"]),
                      "polygon_px": zone["polygon_px"]})
    source: dict = {"width": width, "height": height, "fps": float(counts.get("fps", 25.0)),
                    "realtime": False}
    pattern = sequence_pattern(counts)
    if pattern:
        seq = Path(counts_path).resolve().parent / pattern
        rel = os.path.relpath(seq, Path(out_path).resolve().parent)
        source["url"] = f"images:{rel}"
    return {
        "site": {"name": str(counts.get("clip", Path(counts_path).parent.name)),
                 "description": "made by roadwatch site-from-counts from a hand-count file"},
        "source": source,
        "calibration": {"image_px": cal["image_px"], "road_m": cal["road_m"]},
        "lanes": lanes,
        "loops": loops,
    }


def count_point(poly: np.ndarray, line: list) -> tuple[float, float] | None:
    """Where the count line crosses a lane: the middle of the part of the line segment inside the lane
    polygon (image pixels), or None when it misses the lane. The line may slant across the lanes."""
    a, b = np.asarray(line, dtype=np.float64)
    d = b - a
    ts = []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        e = q - p
        den = d[0] * e[1] - d[1] * e[0]
        if abs(den) < 1e-12:
            continue
        w = p - a
        t = (w[0] * e[1] - w[1] * e[0]) / den
        u = (w[0] * d[1] - w[1] * d[0]) / den
        if 0.0 <= u <= 1.0:
            ts.append(t)
    inside = [t for t in ts if 0.0 <= t <= 1.0]
    if cv2.pointPolygonTest(poly.astype(np.float32), (float(a[0]), float(a[1])), False) >= 0:
        inside.append(0.0)
    if cv2.pointPolygonTest(poly.astype(np.float32), (float(b[0]), float(b[1])), False) >= 0:
        inside.append(1.0)
    if len(inside) < 2 or max(inside) - min(inside) < 1e-9:
        return None
    t = 0.5 * (min(inside) + max(inside))
    return float(a[0] + t * d[0]), float(a[1] + t * d[1])


def image_source_path(site_url: str, site_path: str | Path) -> str:
    """Resolve an ``images:`` source URL relative to the site file."""
    rel = site_url.removeprefix("images:")
    return str(Path(site_path).resolve().parent / rel) if not os.path.isabs(rel) else rel


@click.command(name="site-from-counts")
@click.argument("counts_file", type=click.Path(dir_okay=False))
@click.option("--out", "out_path", required=True, type=click.Path(dir_okay=False), help="site.toml to write")
def site_from_counts(counts_file: str, out_path: str) -> None:
    """Make a site config (calibration, lanes, count line, loops, source) from a hand-count file."""
    import tomli_w

    try:
        counts = load_counts(counts_file)
        data = site_dict_from_counts(counts, counts_file, out_path)
        site = parse_site(json.loads(json.dumps(data)), out_path)
    except (HandCountError, ConfigError) as e:
        raise click.ClickException(str(e)) from None
    Path(out_path).parent.mkdir(parents=True, exist_ok=True)
    Path(out_path).write_text(tomli_w.dumps(data), encoding="utf-8")
    err = site.homography.reprojection_error_m(data["calibration"]["image_px"], data["calibration"]["road_m"])
    click.echo(f"wrote {out_path}: {len(site.lanes)} lanes, {len(site.loops)} loops, "
               f"calibration error mean {err.mean():.2f} m max {err.max():.2f} m")
    for lane in site.lanes:
        click.echo(f"  lane {lane.id} ({lane.direction}): region {lane.region_y_m[0]:.1f}..{lane.region_y_m[1]:.1f} m, "
                   f"count line at {lane.count_y_m:.2f} m")
