"""`roadwatch status`: health, faults, fps, dropped frames, live counts and calls of the service."""

from __future__ import annotations

import json
import time

import click

from tools.fieldtool.common import config_option, iso, service_url, url_option
from tools.fieldtool.statusclient import ServiceError, ServiceUnreachable, StatusClient


def _fmt(v, spec: str = ".1f", none: str = "-") -> str:
    return none if v is None else format(v, spec)


def format_status(st: dict, baseline: dict | None = None) -> str:
    """The status JSON as a terminal table; with ``baseline`` (an earlier status), the counts
    since then per channel and lane (for checking against a manual count)."""
    faults = st.get("faults") or []
    lines = [
        f"site {st.get('site', '?')}  version {st.get('version', '?')}  pid {st.get('pid', '?')}  "
        f"up {_duration(st.get('uptime_s'))}",
        f"fps {_fmt(st.get('fps'))}  frames {st.get('frames', '-')}  dropped {st.get('dropped_frames', '-')}  "
        f"tracked vehicles {st.get('tracked_vehicles', '-')}  period seq {st.get('period_seq', '-')}",
        "health: " + ("OK" if not faults else "FAULT " + ", ".join(map(str, faults))),
        "",
        f"{'ch':>3} {'loop':<8} {'lane':>4} {'call':<6} {'count':>7} {'occ %':>6} {'km/h':>6} {'len m':>6}  "
        + ("since  " if baseline else "") + "classes",
    ]
    base_ch = {c.get("channel"): c.get("count", 0) for c in (baseline or {}).get("channels", [])}
    for ch in st.get("channels", []):
        call = ("FORCED" if ch.get("forced") else "ON") if ch.get("call") else "."
        classes = " ".join(f"{k}:{v}" for k, v in sorted((ch.get("class_counts") or {}).items()))
        lines.append(
            f"{ch.get('channel', '?'):>3} {str(ch.get('loop_id', '')):<8} {ch.get('lane', ''):>4} {call:<6} "
            f"{ch.get('count', 0):>7} {_fmt(ch.get('occupancy_pct')):>6} {_fmt(ch.get('last_speed_kmh')):>6} "
            f"{_fmt(ch.get('last_length_m')):>6}  "
            + (f"{ch.get('count', 0) - base_ch.get(ch.get('channel'), ch.get('count', 0)):>+5}  " if baseline else "")
            + classes
        )
    lanes = st.get("lanes") or {}
    if lanes:
        lines += ["", "live count per lane: " + "  ".join(f"lane {k}: {v}" for k, v in lanes.items())]
        if baseline:
            b = baseline.get("lanes") or {}
            lines.append("since start:         " + "  ".join(f"lane {k}: {v - b.get(k, v):+d}" for k, v in lanes.items()))
    last = st.get("last_period") or []
    if last:
        start = last[0].get("period_start")
        lines += ["", f"last period {iso(start) if start is not None else '?'} ({last[0].get('period_s', '?')} s):"]
        lines.append(f"{'lane':>4} {'count':>6} {'q veh/h':>8} {'k veh/km':>8} {'v km/h':>7} {'occ %':>6} {'v85':>6}")
        for a in last:
            lines.append(
                f"{a.get('lane'):>4} {a.get('count', 0):>6} {_fmt(a.get('flow_vph'), '.0f'):>8} "
                f"{_fmt(a.get('density_vpkm')):>8} {_fmt(a.get('speed_kmh')):>7} {_fmt(a.get('occupancy_pct')):>6} "
                f"{_fmt(a.get('speed85_kmh')):>6}" + ("  partial" if a.get("partial") else "")
            )
    return "\n".join(lines)


def _duration(s) -> str:
    if s is None:
        return "-"
    s = int(s)
    d, s = divmod(s, 86400)
    h, s = divmod(s, 3600)
    m, s = divmod(s, 60)
    return (f"{d}d " if d else "") + f"{h:02d}:{m:02d}:{s:02d}"


@click.command("status")
@config_option
@url_option
@click.option("--once", is_flag=True, help="Print once and exit (default: refresh until Ctrl-C).")
@click.option("--json", "as_json", is_flag=True, help="Print the raw status JSON once (for scripts).")
@click.option("--interval", type=click.FloatRange(min=0.2), default=1.0, show_default=True, help="Refresh period, s.")
@click.option("--count", "n", type=click.IntRange(min=1), default=None, help="Stop after this many refreshes.")
@click.option("--since-start", is_flag=True,
              help="Also show counts since this command started (to compare with a manual count).")
def status(config_path: str, url: str | None, once: bool, as_json: bool, interval: float, n: int | None,
           since_start: bool) -> None:
    """Show health, faults, fps, dropped frames, live counts and calls of the running service.

    Exit status 1 if the service does not answer, 2 if it reports a fault (with --once/--json).

    \b
    Examples:
      roadwatch status                 # refreshing table, Ctrl-C to stop
      roadwatch status --once
      roadwatch status --json | jq .channels
      roadwatch status --since-start   # count by hand alongside, compare the "since" column
    """
    client = StatusClient(service_url(url, config_path))
    if as_json or once:
        try:
            st = client.status()
        except (ServiceError, ServiceUnreachable) as e:
            raise click.ClickException(str(e)) from None
        click.echo(json.dumps(st, indent=2) if as_json else format_status(st))
        if st.get("faults"):
            raise SystemExit(2)
        return
    shown = 0
    baseline = None
    started = time.strftime("%H:%M:%S")
    try:
        while n is None or shown < n:
            try:
                st = client.status()
                if since_start and baseline is None:
                    baseline = st
                text = format_status(st, baseline)
                if baseline is not None:
                    text += f"\n(since {started})"
            except (ServiceError, ServiceUnreachable) as e:
                text = f"{time.strftime('%H:%M:%S')}  {e} (retrying)"
            click.clear()
            click.echo(f"{client.url}  {time.strftime('%Y-%m-%d %H:%M:%S')}  (Ctrl-C to stop)\n{text}")
            shown += 1
            if n is None or shown < n:
                time.sleep(interval)
    except KeyboardInterrupt:
        pass
