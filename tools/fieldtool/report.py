"""`roadwatch report`: PNG plots from the store — flow/speed/occupancy per lane over time and a
time-space diagram of vehicle trajectories (as Fig. 6 of Coifman et al. 1998)."""

from __future__ import annotations

import io
from datetime import datetime, timezone
from pathlib import Path

import click
import numpy as np

from tools.fieldtool.common import When, config_option, iso, write_file
from tools.fieldtool.storeaccess import open_readonly, store_path

LANE_COLOURS = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:gray"]


def _utc(ts) -> list[datetime]:
    return [datetime.fromtimestamp(float(t), timezone.utc) for t in ts]


def _extent(periods: list[dict]) -> tuple[float, float]:
    """Wall-clock span covered by the periods (at least 15 minutes, so one period is readable)."""
    t0 = min(p["period_start"] for p in periods)
    t1 = max(p["period_start"] + p["period_s"] for p in periods)
    pad = max(0.0, 900.0 - (t1 - t0)) / 2
    return t0 - pad, t1 + pad


def _save(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    write_file(path, buf.getvalue())


def plot_periods(periods: list[dict], title: str, path: Path) -> None:
    """Three panels over time, one line per lane: flow (veh/h), speed (km/h), occupancy (%)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt

    lanes = sorted({p["lane"] for p in periods})
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for i, lane in enumerate(lanes):
        rows = [p for p in periods if p["lane"] == lane]
        mid = _utc([p["period_start"] + p["period_s"] / 2 for p in rows])
        col = LANE_COLOURS[i % len(LANE_COLOURS)]
        partial = np.array([bool(p["partial"]) for p in rows])
        for ax, key in zip(axes, ("flow_vph", "speed_kmh", "occupancy_pct")):
            y = np.array([np.nan if p[key] is None else p[key] for p in rows], dtype=float)
            ax.plot(mid, y, "-o", color=col, ms=3, label=f"lane {lane}")
            if partial.any():
                ax.plot(np.array(mid)[partial], y[partial], "o", mfc="white", mec=col, ms=6)
        tms = np.array([np.nan if p["time_mean_speed_kmh"] is None else p["time_mean_speed_kmh"] for p in rows], float)
        axes[1].plot(mid, tms, ":", color=col, lw=1)
    axes[0].set_ylabel("flow q (veh/h)")
    axes[1].set_ylabel("speed (km/h)")
    axes[1].set_title("solid: Edie space-mean speed, dotted: time-mean speed at the count line", fontsize=9)
    axes[2].set_ylabel("occupancy (%)")
    axes[2].set_xlabel("time (UTC); hollow markers: partial periods")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_ylim(0, max(ax.get_ylim()[1], 1.0) * 1.08)
    axes[0].legend(loc="upper right", ncols=max(1, len(lanes)))
    axes[2].set_xlim(*_utc(_extent(periods)))
    axes[2].xaxis.set_major_formatter(mdates.DateFormatter("%m-%d %H:%M", tz=timezone.utc))
    fig.suptitle(title)
    fig.autofmt_xdate()
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def plot_counts(periods: list[dict], title: str, path: Path) -> None:
    """Vehicles per period, one panel per lane, bars stacked by length class."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt

    lanes = sorted({p["lane"] for p in periods})
    classes = sorted({c for p in periods for c in (p["class_counts"] or {})})
    fig, axes = plt.subplots(len(lanes), 1, figsize=(10, 2.6 * len(lanes) + 1.0), sharex=True, squeeze=False)
    for ax, lane in zip(axes[:, 0], lanes):
        rows = [p for p in periods if p["lane"] == lane]
        starts = _utc([p["period_start"] for p in rows])
        width = rows[0]["period_s"] / 86400.0 * 0.85  # bar width in days (matplotlib date units)
        bottom = np.zeros(len(rows))
        for j, cls in enumerate(classes):
            n = np.array([(p["class_counts"] or {}).get(cls, 0) for p in rows], dtype=float)
            ax.bar(starts, n, width=width, bottom=bottom, align="edge", label=cls, color=LANE_COLOURS[j % len(LANE_COLOURS)])
            bottom += n
        other = np.array([p["count"] for p in rows], dtype=float) - bottom
        if (other > 0).any():
            ax.bar(starts, np.clip(other, 0, None), width=width, bottom=bottom, align="edge", label="unclassified", color="0.6")
        ax.set_ylabel(f"lane {lane}\nvehicles / period")
        ax.grid(alpha=0.3, axis="y")
    axes[0, 0].legend(loc="upper right", ncols=max(1, len(classes) + 1), fontsize=8)
    axes[-1, 0].set_xlim(*_utc(_extent(periods)))
    axes[-1, 0].xaxis.set_major_formatter(mdates.DateFormatter("%m-%d %H:%M", tz=timezone.utc))
    axes[-1, 0].set_xlabel("period start (UTC)")
    fig.suptitle(title)
    fig.autofmt_xdate()
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def trajectory_lines(vehicles: list[dict]) -> dict[int, list[tuple[np.ndarray, np.ndarray]]]:
    """Per lane, (wall times, Y positions) of every vehicle with a stored trajectory.

    Trajectory times are monotonic capture seconds; they are placed on the wall clock by
    anchoring the first sample at the vehicle's wall_entry.
    """
    out: dict[int, list] = {}
    for v in vehicles:
        traj = v.get("trajectory")
        if not traj:
            continue
        a = np.asarray(traj, dtype=float)
        if a.ndim != 2 or a.shape[1] < 3 or len(a) < 2:
            continue
        wall = v["wall_entry"] + (a[:, 0] - a[0, 0])
        out.setdefault(v["lane"], []).append((wall, a[:, 2]))
    return out


def site_marks(config_path: str) -> dict[int, list[tuple[str, float, float]]]:
    """Per lane, (label, y0, y1) of its loops and count line from the config, if it loads."""
    from pathlib import Path as _P

    from appliance.config import ConfigError, load_site

    if not _P(config_path).is_file():
        return {}
    try:
        cfg = load_site(config_path)
    except ConfigError:
        return {}
    marks: dict[int, list] = {}
    for lane in cfg.lanes:
        marks.setdefault(lane.id, []).append(("count", lane.count_y_m, lane.count_y_m))
    for lp in cfg.loops:
        marks.setdefault(lp.lane, []).append((f"{lp.id} ch{lp.channel}", lp.y_m, lp.y_m + lp.length_m))
    return marks


def plot_time_space(vehicles: list[dict], title: str, path: Path, t_start: float | None = None,
                    seconds: float | None = None, marks: dict | None = None) -> int:
    """Time-space diagram per lane: distance along the road (Y) against time, over
    [t_start, t_start + seconds) (default: all). Returns the number of trajectories drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = trajectory_lines(vehicles)
    if t_start is not None and seconds is not None:
        lines = {k: [(w, y) for w, y in ls if w[-1] >= t_start and w[0] < t_start + seconds] for k, ls in lines.items()}
        lines = {k: ls for k, ls in lines.items() if ls}
    if not lines:
        return 0
    lanes = sorted(lines)
    fig, axes = plt.subplots(len(lanes), 1, figsize=(10, 3.2 * len(lanes) + 0.8), sharex=True, squeeze=False)
    t0 = t_start if t_start is not None else min(w[0] for ls in lines.values() for w, _ in ls)
    n = 0
    for ax, lane in zip(axes[:, 0], lanes):
        for wall, y in lines[lane]:
            ax.plot(wall - t0, y, "-", color="k", lw=0.8)
            n += 1
        for label, y0, y1 in (marks or {}).get(lane, []):
            if y1 > y0:  # a loop: band, labelled right of the panel
                ax.axhspan(y0, y1, color="tab:red", alpha=0.25, lw=0)
                ax.annotate(label, (1.0, y1), xycoords=("axes fraction", "data"), xytext=(3, 0),
                            textcoords="offset points", fontsize=7, va="center")
            else:  # the count line: dashed, labelled inside on the left
                ax.axhline(y0, color="tab:orange", ls="--", lw=1)
                ax.annotate(label, (0.0, y0), xycoords=("axes fraction", "data"), xytext=(3, 2),
                            textcoords="offset points", fontsize=7, va="bottom", color="tab:orange")
        ax.set_ylabel(f"lane {lane}\ndistance Y (m)")
        ax.grid(alpha=0.3)
        if seconds is not None:
            ax.set_xlim(0, seconds)
    axes[-1, 0].set_xlabel(f"time (s) after {iso(t0)}")
    fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return n


@click.command("report")
@click.option("--from", "t_from", type=When(), required=True, help="Start (ISO 8601 or Unix seconds).")
@click.option("--to", "t_to", type=When(), required=True, help="End (exclusive).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="report", show_default=True,
              help="Directory for the PNGs (created).")
@click.option("--lane", type=int, default=None, help="Only this lane.")
@click.option("--ts-seconds", type=click.FloatRange(min=10), default=180.0, show_default=True,
              help="Length of the time-space diagram window (a long window is unreadable).")
@click.option("--ts-from", type=When(), default=None, help="Start of the time-space window (default: --from).")
@click.option("--db", type=click.Path(dir_okay=False), default=None, help="Store file (default: the config's store.path).")
@config_option
def report(t_from: float, t_to: float, out_dir: str, lane: int | None, ts_seconds: float, ts_from: float | None,
           db: str | None, config_path: str) -> None:
    """Plot flow/speed/occupancy per lane over time and a time-space diagram of trajectories.

    Writes OUT/flow_speed_occupancy.png, OUT/counts_by_class.png and, when trajectories
    are stored (store.trajectories = true), OUT/time_space.png.

    \b
    Example:
      roadwatch report --from 2026-01-01T07:00Z --to 2026-01-01T09:00Z --out am-peak
    """
    if t_to <= t_from:
        raise click.BadParameter("--to must be after --from", param_hint="--to")
    store = open_readonly(store_path(db, config_path))
    try:
        periods = store.periods(t_from, t_to, lane)
        vehicles = store.vehicles(t_from, t_to, lane)
    finally:
        store.close()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    span = f"{iso(t_from)} .. {iso(t_to)}"
    steps = ["periods", "counts", "trajectories"]
    written = []
    with click.progressbar(steps, label="plotting", file=click.get_text_stream("stderr")) as bar:
        for step in bar:
            if step == "periods":
                if not periods:
                    continue
                p = out / "flow_speed_occupancy.png"
                plot_periods(periods, f"Per-lane measures {span}", p)
                written.append(f"{p}: {len(periods)} lane-periods")
            elif step == "counts":
                if not periods:
                    continue
                p = out / "counts_by_class.png"
                plot_counts(periods, f"Vehicles per period by length class {span}", p)
                written.append(f"{p}: {sum(x['count'] for x in periods)} vehicles")
            elif trajectory_lines(vehicles):
                p = out / "time_space.png"
                ts0 = t_from if ts_from is None else ts_from
                n = plot_time_space(vehicles, f"Time-space diagram from {iso(ts0)} ({ts_seconds:g} s)", p,
                                    ts0, ts_seconds, site_marks(config_path))
                written.append(f"{p}: {n} trajectories")
    if not periods:
        click.echo(f"no periods in the store for {span}", err=True)
    if not trajectory_lines(vehicles):
        click.echo(f"no trajectories for {span} ({len(vehicles)} vehicles; set store.trajectories = true to keep them)",
                   err=True)
    if not written:
        raise click.ClickException(f"nothing to plot for {span}")
    for w in written:
        click.echo(f"wrote {w}")
