"""`roadwatch evaluate`: compare replay results with simulator truth or with a hand-count file."""

from __future__ import annotations

import csv
import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import click
import numpy as np

from appliance.config import MeasuresConfig
from appliance.loops import length_class
from tools.loop_classes import MATCH_S, format_loop_classes, scene_loop_classes

if TYPE_CHECKING:
    from tools.edie_parts import LaneParts

TABLE1_BANDS = (2.5, 5.0, 10.0, 15.0, 20.0, 25.0)  # % bands of the paper's Table 1
SPOT_MIN_KMH = 15.0  # spot speeds are compared for vehicles at least this fast (a crawl's relative error says little)


class EvaluateError(ValueError):
    """Results or truth cannot be read (names the file and the problem)."""


# ------------------------------------------------------------------------------------ reading


def _num(v):
    if v is None or v == "":
        return None
    if isinstance(v, (int, float)):
        return v
    try:
        f = float(v)
    except ValueError:
        return v
    return int(f) if f.is_integer() and "." not in str(v) and "e" not in str(v).lower() else f


def read_csv(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with path.open(newline="") as f:
        rows = []
        for r in csv.DictReader(f):
            row = {k: _num(v) for k, v in r.items()}
            for k in ("partial",):
                if k in row and isinstance(row[k], str):
                    row[k] = row[k].lower() == "true"
            if isinstance(row.get("class_counts"), str):
                try:
                    row["class_counts"] = json.loads(row["class_counts"])
                except json.JSONDecodeError:
                    pass
            rows.append(row)
        return rows


def load_results(path: str | Path) -> dict[str, list[dict]]:
    """periods, crossings, loop_events, vehicles from a replay .sqlite or .csv result."""
    p = Path(path)
    if not p.exists():
        raise EvaluateError(f"{p}: no such results file")
    if p.suffix.lower() == ".csv":
        vehicles = read_csv(p.with_name(p.stem + "_vehicles.csv"))
        for v in vehicles:  # the CSV holds VehicleRecord's fields (id); the SQLite table names it vehicle_id
            v.setdefault("vehicle_id", v.get("id"))
        return {
            "periods": read_csv(p),
            "crossings": read_csv(p.with_name(p.stem + "_crossings.csv")),
            "loop_events": read_csv(p.with_name(p.stem + "_loop_events.csv")),
            "vehicles": vehicles,
            "edie_segments": read_csv(p.with_name(p.stem + "_edie_segments.csv")),
        }
    try:
        conn = sqlite3.connect(f"file:{p}?mode=ro", uri=True)
        conn.row_factory = sqlite3.Row
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    except sqlite3.DatabaseError as e:
        raise EvaluateError(f"{p}: not a results CSV or SQLite file ({e})") from None
    if "periods" not in tables:
        raise EvaluateError(f"{p}: has no periods table (not a roadwatch results file)")
    out = {}
    for name in ("periods", "crossings", "loop_events", "vehicles", "edie_segments"):
        out[name] = [dict(r) for r in conn.execute(f"SELECT * FROM {name}")] if name in tables else []
    for r in out["periods"]:
        if isinstance(r.get("class_counts"), str):
            r["class_counts"] = json.loads(r["class_counts"])
        r["partial"] = bool(r.get("partial"))
    conn.close()
    return out


def load_truth(truth_dir: str | Path) -> dict:
    d = Path(truth_dir)
    if not (d / "aggregates.csv").exists():
        raise EvaluateError(f"{d}: no aggregates.csv (not a simulator truth directory)")
    meta = json.loads((d / "meta.json").read_text()) if (d / "meta.json").exists() else {}
    return {
        "periods": read_csv(d / "aggregates.csv"),
        "loop_events": read_csv(d / "loop_events.csv"),
        "vehicles_path": d / "vehicles.csv",
        "meta": meta,
    }


# ------------------------------------------------------------------------------------ comparing


def rel_err_pct(est: float | None, truth: float | None) -> float | None:
    if est is None or truth is None or truth == 0:
        return None
    return 100.0 * (est - truth) / truth


def table1(errors_pct: list[float]) -> dict[float, float]:
    """Share (%) of samples whose absolute error is within each band of the paper's Table 1."""
    e = np.abs(np.asarray(errors_pct, dtype=np.float64))
    if len(e) == 0:
        return {b: float("nan") for b in TABLE1_BANDS}
    return {b: 100.0 * float(np.mean(e <= b)) for b in TABLE1_BANDS}


@dataclass
class TruthComparison:
    lane_counts: dict[int, tuple[int, int]] = field(default_factory=dict)  # lane -> (truth, result)
    pairs: list[tuple[dict, dict]] = field(default_factory=list)  # matched (truth, result) periods
    errors: dict[str, list[float]] = field(default_factory=dict)  # flow/density/speed % errors
    occupancy_pp: list[float] = field(default_factory=list)
    loop_counts: dict[int, tuple[int, int]] = field(default_factory=dict)  # channel -> (truth, result)
    class_counts: dict[str, tuple[int, int]] = field(default_factory=dict)  # length class -> (truth, result)

    def count_error_pct(self, lane: int) -> float:
        t, r = self.lane_counts[lane]
        return 100.0 * (r - t) / t if t else (0.0 if r == 0 else float("inf"))


def period_errors(truth: dict, result: dict) -> dict[str, float]:
    """One lane-period's errors: flow, density and speed in per cent, occupancy in points (where both
    sides have the value)."""
    errors = {}
    for name, col in (("flow", "flow_vph"), ("density", "density_vpkm"), ("speed", "speed_kmh")):
        e = rel_err_pct(result.get(col), truth.get(col))
        if e is not None:
            errors[name] = e
    if truth.get("occupancy_pct") is not None and result.get("occupancy_pct") is not None:
        errors["occupancy"] = float(result["occupancy_pct"]) - float(truth["occupancy_pct"])
    return errors


def compare_with_truth(truth: dict, results: dict, include_partial: bool = True) -> TruthComparison:
    cmp = TruthComparison(errors={"flow": [], "density": [], "speed": []})
    res = {(int(r["lane"]), float(r["period_start"])): r for r in results["periods"]}
    for t in truth["periods"]:
        key = (int(t["lane"]), float(t["period_start"]))
        r = res.get(key)
        if r is None or (not include_partial and (t.get("partial") or r.get("partial"))):
            continue
        cmp.pairs.append((t, r))
        lane = key[0]
        tc, rc = cmp.lane_counts.get(lane, (0, 0))
        cmp.lane_counts[lane] = (tc + int(t["count"]), rc + int(r["count"]))
        for name, e in period_errors(t, r).items():
            (cmp.occupancy_pp if name == "occupancy" else cmp.errors[name]).append(e)
        t_cls, r_cls = t.get("class_counts") or {}, r.get("class_counts") or {}
        add_pair_counts(cmp.class_counts, {name: (int(t_cls.get(name, 0)), int(r_cls.get(name, 0)))
                                           for name in t_cls.keys() | r_cls.keys()})
    for ev, slot in ((truth.get("loop_events", []), 0), (results.get("loop_events", []), 1)):
        for e in ev:
            ch = int(e["channel"])
            c = list(cmp.loop_counts.get(ch, (0, 0)))
            c[slot] += 1
            cmp.loop_counts[ch] = tuple(c)
    return cmp


def add_pair_counts(total: dict[str, tuple[int, int]], more: dict[str, tuple[int, int]]) -> None:
    """Add more's (a, b) counts per name into total's, in place."""
    for name, (a, b) in more.items():
        ta, tb = total.get(name, (0, 0))
        total[name] = (ta + a, tb + b)


def format_class_counts(counts: dict[str, tuple[int, int]]) -> str:
    """Length classes' (truth, result) counts, the default classes in their order first."""
    order = {name: i for i, name in enumerate(MeasuresConfig().length_class_names)}
    return ", ".join(f"{name} {t}/{r}" for name, (t, r) in sorted(counts.items(), key=lambda kv: (
        order.get(kv[0], len(order)), kv[0])))


def format_truth_report(cmp: TruthComparison) -> str:
    lines = ["Per-lane counts (matched periods):", f"  {'lane':>4} {'truth':>6} {'result':>6} {'error %':>8}"]
    for lane in sorted(cmp.lane_counts):
        t, r = cmp.lane_counts[lane]
        lines.append(f"  {lane:>4} {t:>6} {r:>6} {cmp.count_error_pct(lane):>8.1f}")
    lines.append(f"\nPeriod errors, share of samples within (Table 1 form), {len(cmp.pairs)} lane-periods:")
    lines.append("  " + f"{'measure':<8} {'n':>4} " + " ".join(f"{'<=' + str(b) + '%':>7}" for b in TABLE1_BANDS)
                 + f" {'mean %':>7} {'max |%|':>7}")
    for name in ("flow", "density", "speed"):
        e = cmp.errors[name]
        shares = table1(e)
        mean = float(np.mean(e)) if e else float("nan")
        mx = float(np.max(np.abs(e))) if e else float("nan")
        lines.append("  " + f"{name:<8} {len(e):>4} " + " ".join(f"{shares[b]:>7.1f}" for b in TABLE1_BANDS)
                     + f" {mean:>7.2f} {mx:>7.2f}")
    if cmp.occupancy_pp:
        o = np.abs(cmp.occupancy_pp)
        lines.append(f"\nLoop occupancy error: mean |{o.mean():.2f}| pp, max {o.max():.2f} pp over {len(o)} lane-periods")
    if cmp.class_counts:
        lines.append(f"Length classes of the counted vehicles (truth/result): {format_class_counts(cmp.class_counts)}")
    if cmp.loop_counts:
        lines.append("Loop actuations per channel (truth/result): "
                     + ", ".join(f"{ch}: {t}/{r}" for ch, (t, r) in sorted(cmp.loop_counts.items())))
    return "\n".join(lines)


@dataclass
class CountComparison:
    per_lane: dict[int, dict[str, int]] = field(default_factory=dict)  # lane -> matched/missed/extra/hand/result
    matches: list[tuple[dict, dict]] = field(default_factory=list)
    missed: list[dict] = field(default_factory=list)
    extra: list[dict] = field(default_factory=list)


def compare_with_counts(counts: dict, crossings: list[dict], tolerance_frames: int = 4,
                        fps: float | None = None, frame_range: tuple[int, int] | None = None) -> CountComparison:
    """Match result crossings with hand-counted ones: same lane, frames within the tolerance. A result
    crossing's frame is its time t x fps where it has one."""
    fps = fps or float(counts.get("fps", 25.0))
    hand = [dict(c) for c in counts["crossings"]]
    res = []
    for c in crossings:
        c = dict(c)
        if c.get("t") is not None:  # the frame it crossed in ("frame" is where it was seen: a report is held)
            c["frame"] = int(round(float(c["t"]) * fps))
        res.append(c)
    if frame_range is not None:
        lo, hi = frame_range
        hand = [c for c in hand if lo <= c["frame"] <= hi]
        res = [c for c in res if lo <= c["frame"] <= hi]
    cmp = CountComparison()
    lanes = sorted({int(c["lane"]) for c in hand} | {int(c["lane"]) for c in res} | {int(ln["id"]) for ln in counts["lanes"]})
    for lane in lanes:
        h = sorted((c for c in hand if int(c["lane"]) == lane), key=lambda c: c["frame"])
        r = sorted((c for c in res if int(c["lane"]) == lane), key=lambda c: c["frame"])
        cand = sorted(
            (abs(int(a["frame"]) - int(b["frame"])), i, j)
            for i, a in enumerate(h) for j, b in enumerate(r) if abs(int(a["frame"]) - int(b["frame"])) <= tolerance_frames
        )
        used_h, used_r = set(), set()
        for _, i, j in cand:
            if i in used_h or j in used_r:
                continue
            used_h.add(i); used_r.add(j)
            cmp.matches.append((h[i], r[j]))
        missed = [h[i] for i in range(len(h)) if i not in used_h]
        extra = [r[j] for j in range(len(r)) if j not in used_r]
        cmp.missed += missed
        cmp.extra += extra
        cmp.per_lane[lane] = {"hand": len(h), "result": len(r), "matched": len(used_h),
                              "missed": len(missed), "extra": len(extra)}
    return cmp


def truth_crossings(vehicles_path: str | Path, lines: dict[int, float]) -> list[dict]:
    """The simulator's crossings of each lane's count line (lane -> Y in metres): when a vehicle's front
    passes it while in that lane, with its class, visible share and speed then."""
    tracks: dict[str, list[tuple[float, int, float, str, float, float, float]]] = {}
    with open(vehicles_path, newline="") as f:
        for r in csv.DictReader(f):
            tracks.setdefault(r["vehicle_id"], []).append(
                (float(r["t"]), int(r["lane"]), float(r["y_front_m"]), r["class"], float(r["visible_frac"]),
                 float(r["speed_mps"]), float(r["length_m"])))
    out = []
    for vid, rows in tracks.items():
        rows.sort()
        for (t0, lane, y0, cls, vis, v, length), (t1, _, y1, *_) in zip(rows, rows[1:]):
            y = lines.get(lane)
            if y is not None and y1 != y and (y0 - y) * (y1 - y) <= 0:  # a sample on the line: the next pair
                out.append({"lane": lane, "t": t0 + (y - y0) / (y1 - y0) * (t1 - t0), "vehicle_id": vid,
                            "class": cls, "visible": vis, "speed_kmh": 3.6 * v, "sign": 1 if y1 > y0 else -1,
                            "length_m": length})
    return sorted(out, key=lambda c: c["t"])


def compare_crossings_with_truth(truth: dict, crossings: list[dict], tolerance_s: float = 1.0) -> CountComparison:
    """Match result crossings with the truth's, per lane, nearest in time within tolerance_s (the rule of
    the hand counts). A lane's count line is where its result crossings lie; a lane none crossed is
    missing from the comparison."""
    fps = float(truth["meta"].get("fps", 25.0))
    lines = {int(c["lane"]): float(c["y"]) for c in crossings if c.get("y") is not None}
    ref = truth_crossings(truth["vehicles_path"], lines)
    for c in ref:
        c["frame"] = int(round(c["t"] * fps))
    counts = {"crossings": ref, "lanes": [{"id": lane} for lane in lines], "fps": fps}
    return compare_with_counts(counts, crossings, int(round(tolerance_s * fps)), fps=fps)


# What an extra or missed crossing against the simulator's truth most likely is (crossing_error_causes). The
# simulator numbers its lanes across the road, so lanes of one direction whose ids differ by one are neighbours.
WRONG_LANE_S = 0.6  # an extra and a missed crossing this close in neighbouring lanes: one vehicle, wrong lane
# an extra this close in time to a big vehicle's crossing in its lane is a part of it: its rear or trailer just
# after it, or (receding, seen from behind) its top projected ahead of it just before it
PART_S = 1.2
BESIDE_S = 1.0  # an extra this close to a big vehicle's crossing in the next lane: its part (roof, side, shadow)
BIG_CLASSES = ("van", "truck", "bus", "artic")
OCCLUDED_SHARE = 0.5  # a missed vehicle less visible than this at the line was hidden there
EXTRA_CAUSES = ("wrong lane", "part of a big vehicle", "beside a big vehicle", "unexplained")
MISSED_CAUSES = ("wrong lane", "occluded at the line", "seen at the line")


def crossing_error_causes(cmp: CountComparison) -> tuple[list[str], list[str]]:
    """The likely cause of each extra and each missed crossing of a comparison with the simulator's truth
    (in the order of cmp.extra and cmp.missed). An extra paired with a miss in the next lane of its direction
    (the truth's crossings give each lane's) is a vehicle counted in the wrong lane; else it is a part of a big
    vehicle (van, truck, bus, artic) that crossed about then in its lane, or of one beside it in the next lane
    (a roof, flank or shadow seen there), or unexplained. A miss not paired so was occluded at the
    line or seen there."""
    truth = [h for h, _ in cmp.matches] + cmp.missed
    votes: dict[int, int] = {}
    for h in truth:
        votes[int(h["lane"])] = votes.get(int(h["lane"]), 0) + int(h.get("sign", 1))
    sign = {lane: 1 if v >= 0 else -1 for lane, v in votes.items()}

    def next_to(a: int, b: int) -> bool:
        return abs(a - b) == 1 and sign.get(a, 1) == sign.get(b, 1)

    paired: set[int] = set()
    extra_causes = []
    for c in cmp.extra:
        t, lane = float(c["t"]), int(c["lane"])
        swap = sorted((abs(h["t"] - t), i) for i, h in enumerate(cmp.missed)
                      if i not in paired and next_to(int(h["lane"]), lane) and abs(h["t"] - t) <= WRONG_LANE_S)
        if swap:
            paired.add(swap[0][1])
            extra_causes.append("wrong lane")
        elif any(int(h["lane"]) == lane and h["class"] in BIG_CLASSES and abs(t - h["t"]) <= PART_S for h in truth):
            extra_causes.append("part of a big vehicle")
        elif any(next_to(int(h["lane"]), lane) and h["class"] in BIG_CLASSES and abs(t - h["t"]) <= BESIDE_S
                 for h in truth):
            extra_causes.append("beside a big vehicle")
        else:
            extra_causes.append("unexplained")
    missed_causes = ["wrong lane" if i in paired else
                     "occluded at the line" if h["visible"] < OCCLUDED_SHARE else "seen at the line"
                     for i, h in enumerate(cmp.missed)]
    return extra_causes, missed_causes


def cause_counts(cmp: CountComparison, causes: tuple[list[str], list[str]] | None = None) -> dict[str, dict[str, int]]:
    """How many extra and missed crossings each cause of crossing_error_causes (or the causes given) explains."""
    extra, missed = causes or crossing_error_causes(cmp)
    return {"extra": {k: extra.count(k) for k in EXTRA_CAUSES}, "missed": {k: missed.count(k) for k in MISSED_CAUSES}}


def format_causes(counts: dict[str, dict[str, int]]) -> str:
    return "\n".join(f"  {kind:<6} " + ", ".join(f"{k} {n}" for k, n in counts[kind].items())
                     for kind in ("extra", "missed"))


def format_crossing_lists(cmp: CountComparison, near_s: float = 1.0,
                          causes: tuple[list[str], list[str]] | None = None) -> str:
    """Each extra crossing with the truth's crossings of any lane within near_s (what it may be a part
    or shadow of), then each missed vehicle with its class and visible share; each with its likely cause
    (crossing_error_causes, unless given)."""
    ref = [h for h, _ in cmp.matches] + cmp.missed
    extra_causes, missed_causes = causes or crossing_error_causes(cmp)
    lines = []
    for c, cause in sorted(zip(cmp.extra, extra_causes), key=lambda ec: float(ec[0]["t"])):
        t = float(c["t"])
        near = sorted((h for h in ref if abs(h["t"] - t) <= near_s), key=lambda h: abs(h["t"] - t))
        beside = ", ".join(f"lane {h['lane']} {h['class']} {h['vehicle_id']} ({h['t'] - t:+.2f} s)" for h in near)
        length = f", {float(c['length_m']):.1f} m" if c.get("length_m") is not None else ""
        lines.append(f"  extra  lane {c['lane']} t {t:8.2f} s  vehicle {c.get('vehicle_id')}{length}"
                     f"  [{cause}]  truth near: {beside or 'none'}")
    for h, cause in sorted(zip(cmp.missed, missed_causes), key=lambda hc: hc[0]["t"]):
        lines.append(f"  missed lane {h['lane']} t {h['t']:8.2f} s  {h['class']} {h['vehicle_id']}, "
                     f"{100 * h['visible']:.0f} % visible  [{cause}]")
    return "\n".join(lines)


def spot_speed_errors(cmp: CountComparison) -> dict[int, list[float]]:
    """Per lane: the spot-speed errors (%) of the matched crossings, result against truth, for vehicles the
    truth has at SPOT_MIN_KMH or faster."""
    out: dict[int, list[float]] = {}
    for h, r in cmp.matches:
        if r.get("speed_kmh") is None or float(h["speed_kmh"]) < SPOT_MIN_KMH:
            continue
        out.setdefault(int(h["lane"]), []).append(100.0 * (float(r["speed_kmh"]) / float(h["speed_kmh"]) - 1.0))
    return out


def format_spot_speeds(errors: dict[int, list[float]]) -> str:
    """Per lane: the median spot-speed error, the mean |error| and the share within 5 %."""
    if not errors:
        return "  none"
    lines = []
    for lane, e in sorted(errors.items()):
        a = np.array(e)
        lines.append(f"  lane {lane}: median {np.median(a):+.1f} %, mean |error| {np.abs(a).mean():.1f} %, "
                     f"within 5 % {100 * np.mean(np.abs(a) <= 5.0):.0f} % of {len(a)}")
    return "\n".join(lines)


def record_classes_right(cmp: CountComparison, vehicles: list[dict],
                         measures: MeasuresConfig | None = None) -> dict[str, tuple[int, int]]:
    """Per truth vehicle class: of the matched crossings whose vehicle has a record, how many, and how many
    records' lengths fall in the truth length's length class (what the periods' class counts rest on)."""
    m = measures or MeasuresConfig()
    record = {int(v["vehicle_id"]): v.get("length_m") for v in vehicles if v.get("vehicle_id") is not None}
    out: dict[str, tuple[int, int]] = {}
    for h, r in cmp.matches:
        length = record.get(int(r["vehicle_id"])) if r.get("vehicle_id") is not None else None
        if length is None or h.get("length_m") is None:
            continue
        n, right = out.get(h["class"], (0, 0))
        out[h["class"]] = (n + 1, right + (length_class(float(length), m) == length_class(float(h["length_m"]), m)))
    return out


def format_record_classes(right: dict[str, tuple[int, int]]) -> str:
    """One line: per truth class (the most numerous first) the share classed right, of how many."""
    if not right:
        return "  none (write the vehicle records with roadwatch replay --vehicles)"
    ranked = sorted(right.items(), key=lambda kv: -kv[1][0])
    return "  " + ", ".join(f"{cls} {100 * k / n:.0f} % of {n}" for cls, (n, k) in ranked)


def loop_occupancy_vs_counts(counts: dict, loop_events: list[dict], fps: float | None = None) -> list[dict]:
    """Per lane: the results' loop occupancy over the hand count's occupancy frame range, next to the
    hand-count file's (mask-based) value."""
    occ = counts.get("loop_occupancy") or {}
    if not occ.get("lanes") or not occ.get("frames"):
        return []
    fps = fps or float(counts.get("fps", 25.0))
    f0, f1 = occ["frames"]
    t0, t1 = f0 / fps, (f1 + 1) / fps
    rows = []
    for zone in occ["lanes"]:
        lane = int(zone["lane"])
        evs = [e for e in loop_events if int(e["lane"]) == lane]
        channels = sorted({int(e["channel"]) for e in evs})
        if channels:
            evs = [e for e in evs if int(e["channel"]) == channels[0]]
        on = sum(max(0.0, min(float(e["t_off"]), t1) - max(float(e["t_on"]), t0)) for e in evs)
        rows.append({"lane": lane, "hand_pct": 100.0 * float(zone["occupancy"]), "result_pct": 100.0 * on / (t1 - t0),
                     "hand_runs": zone.get("occupancy_runs"),
                     "result_runs": sum(1 for e in evs if float(e["t_off"]) > t0 and float(e["t_on"]) < t1)})
    return rows


def format_count_report(cmp: CountComparison, lists: bool = True, ref: str = "hand") -> str:
    lines = [f"  {'lane':>4} {ref:>5} {'result':>6} {'matched':>7} {'missed':>6} {'extra':>5} {'diff':>5}"]
    for lane, d in sorted(cmp.per_lane.items()):
        lines.append(f"  {lane:>4} {d['hand']:>5} {d['result']:>6} {d['matched']:>7} {d['missed']:>6} {d['extra']:>5} "
                     f"{d['result'] - d['hand']:>+5d}")
    if cmp.missed and lists:
        lines.append("missed (hand frame, lane): " + ", ".join(f"{c['frame']}/{c['lane']}" for c in cmp.missed))
    if cmp.extra and lists:
        lines.append("extra (result frame, lane): " + ", ".join(f"{c['frame']}/{c['lane']}" for c in cmp.extra))
    return "\n".join(lines)


# ------------------------------------------------------------------------------------ command


@click.command(name="evaluate")
@click.option("--results", "results_path", required=True, type=click.Path(dir_okay=False),
              help="replay results (.sqlite or .csv)")
@click.option("--truth", "truth_dir", type=click.Path(file_okay=False), default=None,
              help="simulator truth directory (aggregates.csv, loop_events.csv, vehicles.csv)")
@click.option("--counts", "counts_path", type=click.Path(dir_okay=False), default=None,
              help="hand-count file (counts.json)")
@click.option("--tolerance", type=int, default=4, show_default=True, help="frames for a hand-count match")
@click.option("--complete-only", is_flag=True, help="ignore partial periods")
@click.option("--crossings", "list_crossings", is_flag=True,
              help="truth: match count-line crossings (same lane, within --window) and list the extra and missed ones")
@click.option("--window", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="truth: seconds within which a crossing matches the truth's (a crawl's near end crosses late)")
@click.option("--frames", "frame_range", default=None, metavar="FIRST:LAST",
              help="hand counts: compare only crossings in this frame range (e.g. a partial replay)")
@click.option("--edie-parts", is_flag=True,
              help="truth: split each lane's Edie distance and time by the truth vehicle under each measured track")
@click.option("--config", "site_path", type=click.Path(dir_okay=False), default=None,
              help="site config with the lanes' Edie regions, for --edie-parts [default: site.toml beside --truth]")
@click.option("--plot", "plot_png", type=click.Path(dir_okay=False), default=None, help="scatter plot PNG (Fig. 7)")
@click.option("--errors-png", type=click.Path(dir_okay=False), default=None, help="Table-1 error distribution PNG")
@click.option("--time-space", "ts_png", type=click.Path(dir_okay=False), default=None,
              help="time-space diagram PNG (Fig. 6)")
def evaluate(results_path: str, truth_dir: str | None, counts_path: str | None, tolerance: int, complete_only: bool,
             list_crossings: bool, window: float, frame_range: str | None, edie_parts: bool, site_path: str | None,
             plot_png: str | None, errors_png: str | None, ts_png: str | None) -> None:
    """Compare replay results with simulator truth (--truth) or a hand count (--counts)."""
    if (truth_dir is None) == (counts_path is None):
        raise click.UsageError("give exactly one of --truth DIR or --counts counts.json")
    if counts_path is not None and click.get_current_context().get_parameter_source("window") \
            != click.core.ParameterSource.DEFAULT:
        raise click.UsageError("--window is for --truth crossings; hand counts match within --tolerance frames")
    try:
        results = load_results(results_path)
        if truth_dir:
            truth = load_truth(truth_dir)
            cmp = compare_with_truth(truth, results, include_partial=not complete_only)
            if not cmp.pairs:
                raise EvaluateError(f"{results_path}: no period matches the truth's lanes and period starts "
                                    f"(was the replay --start the simulator's start time?)")
            click.echo(format_truth_report(cmp))
            by_class = scene_loop_classes(truth, results)
            if by_class is not None:
                click.echo(f"\nLoop actuations matched to the truth's (same channel, on within {MATCH_S:g} s), "
                           f"by the truth vehicle's class:")
                click.echo(format_loop_classes(by_class))
            if list_crossings:
                if not results["crossings"]:
                    raise EvaluateError(
                        f"{results_path}: holds no count-line crossings (write it with roadwatch replay)")
                xc = compare_crossings_with_truth(truth, results["crossings"], window)
                click.echo(f"\nCount-line crossings vs the truth's (match = same lane within {window:g} s):")
                click.echo(format_count_report(xc, lists=False, ref="truth"))
                causes = crossing_error_causes(xc)
                click.echo(format_crossing_lists(xc, causes=causes))
                click.echo("Likely causes:")
                click.echo(format_causes(cause_counts(xc, causes)))
                click.echo(f"\nSpot speeds at the count line (matched vehicles at {SPOT_MIN_KMH:.0f} km/h or more):")
                click.echo(format_spot_speeds(spot_speed_errors(xc)))
                click.echo("\nLength class right in the matched vehicles' records, by the truth vehicle's class:")
                click.echo(format_record_classes(record_classes_right(xc, results.get("vehicles", []))))
            if edie_parts:
                click.echo(_edie_parts_report(truth, results, site_path or Path(truth_dir).parent / "site.toml"))
            from tools import plots

            if plot_png:
                plots.scatter_periods(cmp.pairs, plot_png)
                click.echo(f"wrote {plot_png}")
            if errors_png:
                plots.error_distribution(cmp.errors, errors_png)
                click.echo(f"wrote {errors_png}")
            if ts_png:
                plots.time_space(truth["vehicles_path"], results.get("crossings", []), ts_png,
                                 start_wall=float(truth["meta"].get("start_wall", 0.0)),
                                 measured=results.get("vehicles", []))
                click.echo(f"wrote {ts_png}")
        else:
            from tools.handcount import HandCountError, load_counts

            try:
                counts = load_counts(counts_path)
            except HandCountError as e:
                raise EvaluateError(str(e)) from None
            rng = None
            if frame_range:
                try:
                    lo, hi = (int(x) for x in frame_range.split(":"))
                except ValueError:
                    raise click.BadParameter(f"{frame_range!r} is not FIRST:LAST", param_hint="--frames") from None
                rng = (lo, hi)
            if not results["crossings"]:
                raise EvaluateError(f"{results_path}: holds no count-line crossings (write it with roadwatch replay)")
            cmp = compare_with_counts(counts, results["crossings"], tolerance, frame_range=rng)
            click.echo(f"Crossings vs hand count ({counts_path}, match = same lane within {tolerance} frames):")
            click.echo(format_count_report(cmp))
            occ = loop_occupancy_vs_counts(counts, results.get("loop_events", []))
            if occ and results.get("loop_events"):
                click.echo("\nLoop-zone occupancy over the hand count's frame range (hand = from the masks; "
                           "image-based, so higher than a loop's):")
                for row in occ:
                    click.echo(f"  lane {row['lane']}: result {row['result_pct']:.1f} % ({row['result_runs']} actuations), "
                               f"hand {row['hand_pct']:.1f} % ({row['hand_runs']} runs)")
            if plot_png or ts_png or errors_png or edie_parts:
                click.echo("(plots and --edie-parts are made for --truth comparisons only)", err=True)
    except EvaluateError as e:
        raise click.ClickException(str(e)) from None


def edie_parts_of(truth: dict, results: dict, site_path: str | Path) -> list[LaneParts]:
    """tools.edie_parts.edie_parts for a simulator truth and replay results, the lanes' regions from the site."""
    from appliance.config import ConfigError, load_site
    from tools.edie_parts import edie_parts

    if not Path(site_path).exists():
        raise EvaluateError(f"{site_path}: no such site config (--edie-parts takes the lanes' regions from it: "
                            f"give it with --config)")
    try:
        site = load_site(str(site_path))
    except ConfigError as e:
        raise EvaluateError(str(e)) from None
    if not results.get("edie_segments"):
        raise EvaluateError("the results hold no Edie segments (write them with roadwatch replay --vehicles)")
    regions = {lane.id: (float(lane.region_y_m[0]), float(lane.region_y_m[1])) for lane in site.lanes}
    cam = truth["meta"].get("camera") or {}
    return edie_parts(truth["vehicles_path"], results["edie_segments"], regions,
                      float(truth["meta"].get("start_wall", 0.0)),
                      (float(cam["x_m"]), float(cam["height_m"])) if "x_m" in cam and "height_m" in cam else None)


def _edie_parts_report(truth: dict, results: dict, site_path: str | Path) -> str:
    from tools.edie_parts import format_edie_parts, format_total, total_parts

    parts = edie_parts_of(truth, results, site_path)
    return ("\nEdie distance and time counted, by the truth vehicle under each measured track (whole scene; own: "
            "the first track on a vehicle at each moment, the longest first; duplicate: another one then):\n"
            + format_edie_parts(parts) + "\n  all lanes:\n" + format_total(total_parts(parts), indent="    "))
