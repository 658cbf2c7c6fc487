"""`roadwatch sweep`: simulate scenes, replay them and sum their errors against truth in one table.

The accuracy targets are stated over several presets and seeds; this is the command that measures them.
Scenes are rendered once into WORK/PRESET-sSEED/ and reused; each replay writes TAG.sqlite beside them,
so two versions of the tracker can be compared on the same footage.
"""

from __future__ import annotations

import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np

from tools.edie_parts import format_total, total_parts
from tools.evaluate import (EXTRA_CAUSES, MISSED_CAUSES, TABLE1_BANDS, EvaluateError, TruthComparison, add_pair_counts,
                            cause_counts, compare_crossings_with_truth, compare_with_truth, edie_parts_of,
                            format_causes, format_class_counts, format_record_classes, load_results, load_truth,
                            period_errors, record_classes_right, table1)
from tools.loop_classes import format_loop_classes, merge, scene_loop_classes, to_json
from tools.simulate.presets import PRESETS

# The presets the issue's accuracy targets name; the sweep measures two-directions too (both directions in one
# scene, its camera on a pole at the roadside), and sums the targets over all it ran and over these alone
ISSUE_PRESETS = ("free-flow", "dense", "shockwave", "long-shadows", "night", "rain", "wind-shake", "trucks-and-buses")
TARGET_PRESETS = (*ISSUE_PRESETS, "two-directions")
COUNT_TOL_PCT = 3.0
OCC_TOL_PP = 2.0


@dataclass
class Scene:
    preset: str
    seed: int
    dir: Path

    @property
    def name(self) -> str:
        return f"{self.preset}-s{self.seed}"


def run_logged(what: str, cmd: list[str], log: Path) -> None:
    """Run a command with its output in a log file; a failure names what failed and the log."""
    with open(log, "w") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if r.returncode != 0:
        raise click.ClickException(f"{what} failed (exit {r.returncode}); see {log}")


def _prepare(scene: Scene, seconds: float, tag: str, size: tuple[int, int] = (640, 480)) -> Path:
    """Render the scene if it is not there yet, then replay it into TAG.sqlite (always afresh)."""
    roadwatch = [sys.executable, "-m", "tools.cli"]
    scene.dir.mkdir(parents=True, exist_ok=True)
    meta = scene.dir / "truth" / "meta.json"
    if meta.exists():
        m = json.loads(meta.read_text())
        had = (m.get("seconds"), (m.get("width"), m.get("height")))
        if had != (seconds, size):
            raise click.ClickException(f"{scene.dir} holds a {had[0]} s {had[1][0]}x{had[1][1]} scene, not "
                                       f"{seconds:g} s {size[0]}x{size[1]}: use another --work")
    else:
        run_logged(f"simulating {scene.name}",
                   roadwatch + ["simulate", "--preset", scene.preset, "--seed", str(scene.seed), "--seconds",
                                str(seconds), "--out", str(scene.dir), "--quiet", "--width", str(size[0]), "--height",
                                str(size[1])],
                   scene.dir / "simulate.log")
    out = scene.dir / f"{tag}.sqlite"
    out.unlink(missing_ok=True)
    run_logged(f"replaying {scene.name}", roadwatch + ["replay", str(scene.dir / "video.mp4"), "--config",
                                                       str(scene.dir / "site.toml"), "--out", str(out), "--vehicles"],
               scene.dir / f"{tag}.log")
    return out


def _lane_rows(name: str, whole: TruthComparison, periods: TruthComparison) -> list[dict]:
    """One row per lane: its count over the whole scene, its errors over the compared periods."""
    rows = []
    for lane in sorted(whole.lane_counts):
        t, r = whole.lane_counts[lane]
        row = {"scene": name, "lane": lane, "truth": t, "result": r, "count_err_pct": whole.count_error_pct(lane)}
        errors = [period_errors(tp, rp) for tp, rp in periods.pairs if int(tp["lane"]) == lane]
        for key in ("flow", "density", "speed"):
            row[f"{key}_err_pct"] = [e[key] for e in errors if key in e]
        row["occupancy_err_pp"] = [e["occupancy"] for e in errors if "occupancy" in e]
        rows.append(row)
    return rows


def summarise(rows: list[dict]) -> dict:
    """The targets' measures over all lanes: shares of lanes and lane-periods within each tolerance."""
    counts = [r["count_err_pct"] for r in rows]
    occ = [e for r in rows for e in r["occupancy_err_pp"]]
    out = {
        "lanes": len(counts),
        "counts_within_3pct": sum(abs(e) <= COUNT_TOL_PCT for e in counts),
        "occupancy_samples": len(occ),
        "occupancy_within_2pp": sum(abs(e) <= OCC_TOL_PP for e in occ),
        "occupancy_mean_abs_pp": float(np.mean(np.abs(occ))) if occ else float("nan"),
    }
    for name in ("flow", "density", "speed"):
        e = [x for r in rows for x in r[f"{name}_err_pct"]]
        out[name] = {"n": len(e), "table1": table1(e), "mean_pct": float(np.mean(e)) if e else float("nan")}
    return out


def issue_rows(rows: list[dict]) -> list[dict]:
    """The rows of the scenes of ISSUE_PRESETS (a row's scene is PRESET-sSEED)."""
    return [r for r in rows if r["scene"].rsplit("-s", 1)[0] in ISSUE_PRESETS]


def format_targets(summary: dict) -> str:
    """The four targets' shares of a summary on one line."""
    s = summary
    return (f"counts within {COUNT_TOL_PCT:g} % {s['counts_within_3pct']}/{s['lanes']}; flow within 5 % "
            f"{s['flow']['table1'][5.0]:.1f} %, speed within 2.5 % {s['speed']['table1'][2.5]:.1f} % of "
            f"{s['flow']['n']} lane-periods; occupancy within {OCC_TOL_PP:g} pp "
            f"{s['occupancy_within_2pp']}/{s['occupancy_samples']}")


def format_sweep(rows: list[dict], summary: dict, complete_only: bool) -> str:
    fmt = lambda xs: " ".join(f"{x:+.1f}" for x in xs) or "-"  # noqa: E731
    lines = [f"{'scene':<24} {'lane':>4} {'truth':>5} {'result':>6} {'count %':>7}   {'flow %':<13} "
             f"{'density %':<13} {'speed %':<13} {'occupancy pp':<13}"]
    for r in rows:
        lines.append(f"{r['scene']:<24} {r['lane']:>4} {r['truth']:>5} {r['result']:>6} {r['count_err_pct']:>+7.1f}   "
                     f"{fmt(r['flow_err_pct']):<13} {fmt(r['density_err_pct']):<13} {fmt(r['speed_err_pct']):<13} "
                     f"{fmt(r['occupancy_err_pp']):<13}")
    s = summary
    kind = "complete 5-minute" if complete_only else "all (partial included)"
    lines += ["", f"Lane counts (whole scenes) within {COUNT_TOL_PCT:g} %: {s['counts_within_3pct']}/{s['lanes']}",
              f"Loop occupancy within {OCC_TOL_PP:g} pp: {s['occupancy_within_2pp']}/{s['occupancy_samples']} "
              f"(mean |error| {s['occupancy_mean_abs_pp']:.2f} pp)",
              f"Lane-periods ({kind}) within:  " + " ".join(f"{'<=' + str(b) + '%':>7}" for b in TABLE1_BANDS)
              + f" {'mean %':>7}"]
    for name in ("flow", "density", "speed"):
        m = s[name]
        lines.append(f"  {name:<8} n={m['n']:<4}{'':<24}" + " ".join(f"{m['table1'][b]:>7.1f}" for b in TABLE1_BANDS)
                     + f" {m['mean_pct']:>7.2f}")
    return "\n".join(lines)


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--presets", default=",".join(TARGET_PRESETS), show_default=True, help="Comma-separated presets.")
@click.option("--seeds", default="11", show_default=True, help="Comma-separated seeds.")
@click.option("--seconds", type=click.FloatRange(min=10), default=320.0, show_default=True,
              help="Scene length (one 5-minute period plus the start).")
@click.option("--work", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Directory for the scenes (reused) and the replays.")
@click.option("--size", default="640x480", show_default=True, help="Frame size of the scenes rendered, WxH.")
@click.option("--tag", default="results", show_default=True, help="Name of this run's results files.")
@click.option("--no-replay", is_flag=True, help="Only evaluate the TAG results already there.")
@click.option("--jobs", "-j", type=click.IntRange(min=1), default=1, show_default=True, help="Scenes in parallel.")
@click.option("--partial/--complete-only", "partial", default=False, show_default=True,
              help="Also compare the partial periods (a scene's last minutes).")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the per-scene errors and the summary as JSON.")
def sweep(presets: str, seeds: str, seconds: float, work: Path, size: str, tag: str, no_replay: bool, jobs: int,
          partial: bool, json_out: Path | None) -> None:
    """Simulate, replay and evaluate several scenes; print per-scene errors and the targets' shares.

    \b
    Example (the issue's accuracy targets, two seeds, both cores):
      roadwatch sweep --seeds 11,12 --work sweep -j 2
    """
    names = [p.strip() for p in presets.split(",") if p.strip()]
    unknown = [p for p in names if p not in PRESETS]
    if unknown:
        raise click.BadParameter(f"unknown preset(s): {', '.join(unknown)}", param_hint="--presets")
    try:
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except ValueError:
        raise click.BadParameter(f"{seeds!r} is not a comma-separated list of integers", param_hint="--seeds") from None
    try:
        wh = tuple(int(v) for v in size.lower().split("x"))
    except ValueError:
        wh = ()
    if len(wh) != 2 or min(wh) < 64:
        raise click.BadParameter(f"{size!r} is not WIDTHxHEIGHT (e.g. 1280x720)", param_hint="--size")
    scenes = [Scene(p, s, work / f"{p}-s{s}") for s in seed_list for p in names]
    if not no_replay:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            futures = {sc.name: pool.submit(_prepare, sc, seconds, tag, wh) for sc in scenes}
            for sc in scenes:
                futures[sc.name].result()
                click.echo(f"replayed {sc.name}", err=True)
    rows = []
    causes: dict[str, dict] = {}
    parts: dict[str, dict] = {}
    lanes = []  # every scene's lanes, for the Edie parts' sums
    loops = []  # every scene's loop actuations by class
    classes: dict[str, tuple[int, int]] = {}  # length class -> (truth, result) counts over the whole scenes
    records: dict[str, tuple[int, int]] = {}  # truth class -> (matched vehicles with a record, classed right)
    # how many scenes each encoder wrote: the same scene encoded by OpenCV's mp4v instead of ffmpeg's H.264
    # replays differently, so sweeps compare only on footage from one encoder
    encoders: dict[str, int] = {}
    for sc in scenes:
        try:
            truth, results = load_truth(sc.dir / "truth"), load_results(sc.dir / f"{tag}.sqlite")
        except EvaluateError as e:
            raise click.ClickException(str(e)) from None
        whole = compare_with_truth(truth, results, include_partial=True)
        periods = compare_with_truth(truth, results, include_partial=partial)
        rows += _lane_rows(sc.name, whole, periods)
        add_pair_counts(classes, whole.class_counts)
        enc = truth["meta"].get("encoder", "unknown")
        encoders[enc] = encoders.get(enc, 0) + 1
        if results["crossings"]:
            xc = compare_crossings_with_truth(truth, results["crossings"])
            causes[sc.name] = cause_counts(xc)
            add_pair_counts(records, record_classes_right(xc, results.get("vehicles", [])))
        by_class = scene_loop_classes(truth, results)
        if by_class is not None:
            loops.append(by_class)
        if results.get("edie_segments"):
            scene_lanes = edie_parts_of(truth, results, sc.dir / "site.toml")
            parts[sc.name] = total_parts(scene_lanes)
            lanes += scene_lanes
    summary = summarise(rows)
    click.echo(format_sweep(rows, summary, complete_only=not partial))
    mine = issue_rows(rows)
    summary_issue = summarise(mine) if mine and len(mine) < len(rows) else None
    if summary_issue is not None:
        others = ", ".join(p for p in names if p not in ISSUE_PRESETS)
        click.echo(f"The issue's presets alone (without {others}): {format_targets(summary_issue)}")
    click.echo("Scenes encoded with: " + "; ".join(f"{e} ({n})" for e, n in encoders.items()))
    if classes:
        click.echo(f"Length classes of the counted vehicles (whole scenes), truth/result: {format_class_counts(classes)}")
    total = {kind: {k: sum(c[kind][k] for c in causes.values()) for k in names}
             for kind, names in (("extra", EXTRA_CAUSES), ("missed", MISSED_CAUSES))}
    if causes:
        click.echo(f"Count-line crossings against the truth's, extra and missed by likely cause "
                   f"({len(causes)} scenes):")
        click.echo(format_causes(total))
    if records:
        click.echo(f"Length class right in the matched vehicles' records, by the truth vehicle's class "
                   f"({len(causes)} scenes; as evaluate --crossings):")
        click.echo(format_record_classes(records))
    parts_total = total_parts(lanes) if parts else {}
    if parts:
        click.echo(f"Edie distance and time counted, by the truth vehicle under each track ({len(parts)} scenes; "
                   f"as evaluate --edie-parts):")
        click.echo(format_total(parts_total))
    loop_total = merge(loops)
    if loops:
        click.echo(f"Loop actuations matched to the truth's, by the truth vehicle's class ({len(loops)} scenes; "
                   f"as evaluate):")
        click.echo(format_loop_classes(loop_total))
    if json_out:
        json_out.write_text(json.dumps({"tag": tag, "scenes": rows, "summary": summary,
                                        "summary_issue_presets": summary_issue, "causes": causes,
                                        "causes_total": total, "edie_parts": parts, "edie_parts_total": parts_total,
                                        "loop_classes": to_json(loop_total), "encoders": encoders,
                                        "class_counts": classes, "record_classes_right": records},
                                       indent=1, default=lambda o: str(o)))
