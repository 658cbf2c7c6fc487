"""`roadwatch clip-variants`: a hand-counted clip changed the ways other sites' footage differs, each replayed and
compared with the same hand counts (the real-clip target: every lane within 1 vehicle).

A variant keeps the clip's traffic and counts; only the picture (or its timing) changes, so what it shows is how
the tracker copes with that difference. Variants are built once into WORK/KIND/ and reused; each run replays them
into TAG.sqlite.
"""

from __future__ import annotations

import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import click
import cv2
import numpy as np

from tools.evaluate import compare_with_counts, load_results
from tools.handcount import HandCountError, load_counts
from tools.sweep import run_logged

KINDS = {
    "original": "the clip as it is (with --pad-right: only padded)",
    "reversed": "played backwards: receding traffic entering over the image's bottom edge",
    "dark": "30 % brightness with sensor noise",
    "dusk": "gamma 2.2 at 60 %, strong sensor noise",
    "drift": "the picture shifting 20 px right and 10 px down over the clip, with 2 px of wind shake",
    "dark-drift": "dark and drifting together (a windy night)",
    "repeat": "every other frame a repeat (half-rate footage in a full-rate stream)",
    "fps15": "15 frames/s: frames dropped from the clip's rate",
    "interlace": "each frame's odd rows from the frame before (a field apart)",
    "jpeg": "JPEG quality 25 (compression blocks)",
    "blur": "defocused (Gaussian blur, sigma 1.5 px)",
    "rain": "washed out, rain streaks, noise",
    "up2": "twice the size (a higher-resolution camera)",
    "up4": "four times the size (an HD camera, worked at the working width)",
    "half": "half the size (a low-resolution camera)",
}
DEFAULT_KINDS = ("original", "reversed", "dark", "drift", "dark-drift", "repeat", "fps15", "interlace", "jpeg", "blur",
                 "rain", "up2", "up4")
SCALE = {"up2": 2.0, "up4": 4.0, "half": 0.5}
MAX_LANE_DIFF = 1  # the real-clip target


def _scaled(p, s: float):
    if isinstance(p, list) and p and isinstance(p[0], (int, float)):
        return [v * s for v in p]
    return [_scaled(q, s) for q in p]


def make_variant(counts_file: Path, out_dir: Path, kind: str, pad_right: int = 0) -> Path:
    """Write the variant's frames (out_dir/input/inNNNNNN.jpg) and its hand-count file; returns that file.
    pad_right adds black columns on the right (pixels of the clip's own size): a frame cropped from a larger
    picture can so get back the principal point at its centre that the camera model assumes."""
    if kind not in KINDS:
        raise ValueError(f"unknown variant {kind!r}; known: {', '.join(KINDS)}")
    c = json.loads(counts_file.read_text())
    n = int(c["frames"])
    src = counts_file.parent / "input"
    (out_dir / "input").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    s = SCALE.get(kind, 1.0)
    keep = list(range(n))
    if kind == "fps15":
        fps = float(c.get("fps", 25.0))
        keep = [i for i in range(n) if i == 0 or int(i * 15.0 / fps) != int((i - 1) * 15.0 / fps)]
    prev = None
    for k, i in enumerate(keep):
        dst = out_dir / "input" / f"in{k + 1:06d}.jpg"
        j = n - 1 - i if kind == "reversed" else (i - i % 2 if kind == "repeat" else i)
        if kind in ("original", "reversed") and not pad_right:  # the clip's own frames, in another order
            dst.unlink(missing_ok=True)
            dst.symlink_to((src / f"in{j + 1:06d}.jpg").resolve())
            continue
        img = cv2.imread(str(src / f"in{j + 1:06d}.jpg"))
        if img is None:
            raise ValueError(f"{src / f'in{j + 1:06d}.jpg'}: cannot read the clip's frame")
        quality = 95
        if s != 1.0:
            img = cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)),
                             interpolation=cv2.INTER_CUBIC if s > 1 else cv2.INTER_AREA)
        if kind in ("drift", "dark-drift"):
            dx, dy = 20.0 * i / n + 2.0 * np.sin(0.7 * i), 10.0 * i / n + 1.5 * np.cos(0.9 * i)
            img = cv2.warpAffine(img, np.float32([[1, 0, dx], [0, 1, dy]]), (img.shape[1], img.shape[0]),
                                 borderMode=cv2.BORDER_REPLICATE)
        if kind in ("dark", "dark-drift"):
            img = np.clip(img * 0.3 + rng.normal(0.0, 4.0, img.shape), 0, 255).astype(np.uint8)
        elif kind == "dusk":
            img = np.clip(255 * (img / 255.0) ** 2.2 * 0.6 + rng.normal(0, 6, img.shape), 0, 255).astype(np.uint8)
        elif kind == "interlace":
            cur = img.copy()
            if prev is not None:
                img[1::2] = prev[1::2]
            prev = cur
        elif kind == "jpeg":
            quality = 25
        elif kind == "blur":
            img = cv2.GaussianBlur(img, (0, 0), 1.5)
        elif kind == "rain":
            f = img * 0.8 + 30.0
            for _ in range(120):
                x, y = int(rng.integers(0, img.shape[1])), int(rng.integers(0, img.shape[0]))
                cv2.line(f, (x, y), (x + 2, y + 12), (200, 200, 200), 1)
            img = np.clip(cv2.GaussianBlur(f, (0, 0), 0.7) + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8)
        if pad_right:
            img = cv2.copyMakeBorder(img, 0, 0, 0, round(pad_right * s), cv2.BORDER_CONSTANT, value=(0, 0, 0))
        cv2.imwrite(str(dst), img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if s != 1.0:
        for lane in c["lanes"]:
            lane["polygon_px"] = _scaled(lane["polygon_px"], s)
        c["count_line_px"] = _scaled(c["count_line_px"], s)
        c["calibration"]["image_px"] = _scaled(c["calibration"]["image_px"], s)
        c["calibration"].pop("homography_img_to_road", None)
        for zone in (c.get("loop_occupancy") or {}).get("lanes", []):
            if "polygon_px" in zone:
                zone["polygon_px"] = _scaled(zone["polygon_px"], s)
    c["size"] = [round(c["size"][0] * s) + round(pad_right * s), round(c["size"][1] * s)]
    if kind == "fps15":
        where = {i: k for k, i in enumerate(keep)}
        c["fps"] = 15.0
        for x in c["crossings"]:
            x["frame"] = where.get(x["frame"], where.get(x["frame"] - 1, where.get(x["frame"] + 1, 0)))
    c["frames"] = len(keep)
    if kind == "reversed":
        c["direction"] = "receding"
        for lane in c["lanes"]:
            lane["direction"] = "receding"
        for x in c["crossings"]:
            x["frame"] = n - 1 - x["frame"]
        c["crossings"].sort(key=lambda x: x["frame"])
    p = out_dir / "counts.json"
    p.write_text(json.dumps(c))
    return p


def _run_variant(counts_file: Path, work: Path, kind: str, pad_right: int, tag: str) -> dict:
    """Build (once), make the site, replay and compare one variant; its per-lane rows."""
    d = work / (f"p{pad_right}-{kind}" if pad_right else kind)
    counts_path = d / "counts.json"
    if not counts_path.exists():
        make_variant(counts_file, d, kind, pad_right)
    roadwatch = [sys.executable, "-m", "tools.cli"]
    counts = json.loads(counts_path.read_text())
    site, out = d / f"{tag}.toml", d / f"{tag}.sqlite"
    out.unlink(missing_ok=True)
    for what, cmd in (("site-from-counts", ["site-from-counts", str(counts_path), "--out", str(site)]),
                      ("replay", ["replay", str(d / "input" / "in%06d.jpg"), "--config", str(site), "--fps",
                                  str(counts.get("fps", 25.0)), "--out", str(out), "--vehicles"])):
        run_logged(f"{kind}: {what}", roadwatch + cmd, d / f"{tag}.{what}.log")
    cmp = compare_with_counts(counts, load_results(out)["crossings"])
    return {"kind": d.name, "lanes": {int(k): v for k, v in cmp.per_lane.items()}}


@click.command("clip-variants")
@click.argument("counts_path", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--work", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Directory for the variants (reused) and the replays.")
@click.option("--kinds", default=",".join(DEFAULT_KINDS), show_default=True,
              help=f"Comma-separated variants: {', '.join(KINDS)}.")
@click.option("--pad-right", type=click.IntRange(min=0), default=0, show_default=True,
              help="Black columns added on the right of every variant (pixels of the clip's size); the "
                   "variants are built into WORK/pPX-KIND.")
@click.option("--tag", default="results", show_default=True, help="Name of this run's files.")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=1, show_default=True, help="Variants in parallel.")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the rows as JSON.")
def clip_variants(counts_path: Path, work: Path, kinds: str, pad_right: int, tag: str, jobs: int,
                  json_out: Path | None) -> None:
    """Replay a hand-counted clip changed the ways other sites' footage differs; per-lane counts against the
    hand count for each variant, FAIL where a lane is off by more than 1.

    \b
    Example (the real clip, both cores):
      roadwatch clip-variants ../shared/data/cdnet-highway/counts.json --work variants -j 2
    """
    names = [k.strip() for k in kinds.split(",") if k.strip()]
    unknown = [k for k in names if k not in KINDS]
    if unknown or not names:
        raise click.BadParameter(f"unknown variant(s): {', '.join(unknown) or '(none given)'}; known: "
                                 f"{', '.join(KINDS)}", param_hint="--kinds")
    try:
        load_counts(counts_path)
    except HandCountError as e:
        raise click.ClickException(str(e)) from None
    work.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        rows = list(pool.map(lambda k: _run_variant(counts_path, work, k, pad_right, tag), names))
    fails = 0
    width = max(len("variant"), *(len(r["kind"]) for r in rows))
    click.echo(f"{'variant':{width}s} " + "  ".join(f"lane {lane}: hand result diff" for lane in sorted(rows[0]['lanes'])))
    for r in rows:
        bad = any(abs(v["result"] - v["hand"]) > MAX_LANE_DIFF for v in r["lanes"].values())
        fails += bad
        cells = (f"{'':7s}{v['hand']:4d} {v['result']:6d} {v['result'] - v['hand']:+4d}"
                 for _, v in sorted(r["lanes"].items()))
        click.echo(f"{r['kind']:{width}s} " + "  ".join(cells) + ("  FAIL" if bad else ""))
    click.echo(f"{len(rows) - fails} of {len(rows)} variants within {MAX_LANE_DIFF} vehicle of the hand count in "
               f"every lane")
    if json_out:
        json_out.write_text(json.dumps({"tag": tag, "pad_right": pad_right, "rows": rows}, indent=1))

