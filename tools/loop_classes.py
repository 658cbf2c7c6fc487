"""Loop actuations against the simulator's, by vehicle class: how long each class held its loop and the length
it was measured at (what occupancy and the length classes rest on)."""

from __future__ import annotations

import bisect
import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from appliance.config import MeasuresConfig
from appliance.loops import length_class

# A result actuation is the truth's if it is on the same channel and comes on this close in time (a loop call
# comes on as the front reaches the loop: a near end found a frame or two late is still that vehicle).
MATCH_S = 0.4


@dataclass
class ClassLoops:
    """One vehicle class's actuations: the truth's, those matched, and their on-times and lengths."""

    truth: int = 0
    matched: int = 0
    on_truth_s: float = 0.0  # over the matched actuations
    on_result_s: float = 0.0
    lengths: list[tuple[float, float]] = field(default_factory=list)  # (truth, result) where both are known

    def class_right(self, measures: MeasuresConfig | None = None) -> float | None:
        """Share of the actuations with both lengths whose measured length falls in the truth length's class
        (the default length classes unless measures gives others)."""
        if not self.lengths:
            return None
        m = measures or MeasuresConfig()
        return sum(length_class(t, m) == length_class(r, m) for t, r in self.lengths) / len(self.lengths)

    def length_medians(self) -> tuple[float, float] | None:
        if not self.lengths:
            return None
        a = np.asarray(self.lengths)
        return float(np.median(a[:, 0])), float(np.median(a[:, 1]))


def truth_classes(vehicles_path: str | Path) -> dict[int, str]:
    """Each simulated vehicle's class, from the truth's vehicles.csv."""
    out: dict[int, str] = {}
    with open(vehicles_path, newline="") as f:
        for r in csv.DictReader(f):
            out.setdefault(int(r["vehicle_id"]), r["class"])
    return out


def _length(event: dict) -> float | None:
    v = event.get("length_m")  # as read by tools.evaluate: a number, or None where the loop measured none
    return None if v is None else float(v)


def loop_classes(truth_events: list[dict], result_events: list[dict], classes: dict[int, str],
                 match_s: float = MATCH_S) -> dict[str, ClassLoops]:
    """Match each truth actuation with the nearest unmatched result actuation of its channel coming on within
    match_s, and sum them by the truth vehicle's class."""
    by_channel: dict[int, list[tuple[float, float, float | None]]] = {}
    for e in result_events:
        by_channel.setdefault(int(e["channel"]), []).append(
            (float(e["t_on"]), float(e["t_off"]), _length(e)))
    ons = {}
    for ch, evs in by_channel.items():
        evs.sort(key=lambda r: r[0])
        ons[ch] = [r[0] for r in evs]
    used: set[tuple[int, int]] = set()
    out: dict[str, ClassLoops] = {}
    for e in sorted(truth_events, key=lambda e: float(e["t_on"])):
        ch, on = int(e["channel"]), float(e["t_on"])
        c = out.setdefault(classes.get(int(e["vehicle_id"]), "?"), ClassLoops())
        c.truth += 1
        times = ons.get(ch, [])
        window = range(bisect.bisect_left(times, on - match_s), bisect.bisect_right(times, on + match_s))
        cands = [(abs(times[i] - on), i) for i in window if (ch, i) not in used]
        if not cands:
            continue
        i = min(cands)[1]
        used.add((ch, i))
        r_on, r_off, r_len = by_channel[ch][i]
        c.matched += 1
        c.on_truth_s += float(e["t_off"]) - on
        c.on_result_s += r_off - r_on
        t_len = _length(e)
        if t_len is not None and r_len is not None:
            c.lengths.append((t_len, r_len))
    return out


def scene_loop_classes(truth: dict, results: dict) -> dict[str, ClassLoops] | None:
    """loop_classes for one scene as tools.evaluate loads it (truth dir, results), or None where either side
    has no loop actuations."""
    if not truth["loop_events"] or not results.get("loop_events"):
        return None
    return loop_classes(truth["loop_events"], results["loop_events"], truth_classes(truth["vehicles_path"]))


def merge(parts: list[dict[str, ClassLoops]]) -> dict[str, ClassLoops]:
    """Several scenes' class sums as one."""
    out: dict[str, ClassLoops] = {}
    for p in parts:
        for name, c in p.items():
            m = out.setdefault(name, ClassLoops())
            m.truth += c.truth
            m.matched += c.matched
            m.on_truth_s += c.on_truth_s
            m.on_result_s += c.on_result_s
            m.lengths += c.lengths
    return out


def format_loop_classes(rows: dict[str, ClassLoops], indent: str = "  ") -> str:
    lines = [f"{indent}{'class':<11} {'truth':>5} {'matched':>7}   {'on-time result/truth':<24} "
             f"{'length result/truth (medians)':<31} {'class right'}"]
    for name in sorted(rows, key=lambda n: -rows[n].truth):
        c = rows[name]
        on = (f"{c.on_result_s:7.1f}/{c.on_truth_s:.1f} s ({100 * (c.on_result_s / c.on_truth_s - 1):+.0f} %)"
              if c.on_truth_s > 0 else "-")
        med = c.length_medians()
        ln = f"{med[1]:5.1f}/{med[0]:.1f} m" if med else "-"
        right = c.class_right()
        cr = f"{100 * right:5.0f} %" if right is not None else "-"
        lines.append(f"{indent}{name:<11} {c.truth:>5} {c.matched:>7}   {on:<24} {ln:<31} {cr}")
    return "\n".join(lines)


def to_json(rows: dict[str, ClassLoops]) -> dict:
    out = {}
    for name, c in rows.items():
        med = c.length_medians()
        out[name] = {"truth": c.truth, "matched": c.matched, "on_truth_s": round(c.on_truth_s, 2),
                     "on_result_s": round(c.on_result_s, 2),
                     "length_truth_m": med and round(med[0], 2), "length_result_m": med and round(med[1], 2),
                     "class_right": c.class_right()}
    return out
