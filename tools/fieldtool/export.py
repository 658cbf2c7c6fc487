"""`roadwatch export`: periods, loop events or vehicles from the store as CSV or JSON (read-only)."""

from __future__ import annotations

import csv
import io
import json
import sys
import time

import click

from appliance.store import Store
from tools.fieldtool.common import When, config_option, iso, write_file
from tools.fieldtool.storeaccess import open_readonly, store_path

TIME_COLUMNS = {"periods": "period_start", "loop-events": "wall_on", "vehicles": "wall_exit", "health": "wall"}


def fetch(store: Store, what: str, t0: float, t1: float, lane: int | None, trajectories: bool = False) -> list[dict]:
    """Rows of one table for [t0, t1), optionally one lane, with ISO 8601 copies of the times
    (``<column>_utc``)."""
    if what == "periods":
        rows = store.periods(t0, t1, lane)
    elif what == "loop-events":
        rows = [r for r in store.loop_events(t0, t1) if lane is None or r["lane"] == lane]
    elif what == "health":
        rows = store.health_events(t0, t1)
    else:
        rows = store.vehicles(t0, t1, lane)
        if not trajectories:
            for r in rows:
                r.pop("trajectory", None)
    for r in rows:
        for k in ("period_start", "wall_on", "wall_off", "wall_entry", "wall_exit", "wall"):
            if k in r and r[k] is not None:
                r[f"{k}_utc"] = iso(r[k])
    return rows


def to_csv(rows: list[dict]) -> str:
    if not rows:
        return ""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: json.dumps(v, sort_keys=True) if isinstance(v, (dict, list)) else v for k, v in r.items()})
    return buf.getvalue()


@click.command("export")
@click.option("--from", "t_from", type=When(), required=True, help="Start (ISO 8601 or Unix seconds), inclusive.")
@click.option("--to", "t_to", type=When(), default=None, help="End, exclusive (default: now).")
@click.option("--lane", type=int, default=None, help="Only this lane.")
@click.option("--what", type=click.Choice(list(TIME_COLUMNS)), default="periods", show_default=True)
@click.option("--csv", "fmt", flag_value="csv", default=True, help="CSV with a header row (default).")
@click.option("--json", "fmt", flag_value="json", help="A JSON list of objects.")
@click.option("--trajectories", is_flag=True, help="Vehicles: include the trajectory JSON.")
@click.option("--out", "-o", type=click.Path(dir_okay=False), default=None, help="File to write (default: stdout).")
@click.option("--db", type=click.Path(dir_okay=False), default=None, help="Store file (default: the config's store.path).")
@config_option
def export(t_from: float, t_to: float | None, lane: int | None, what: str, fmt: str, trajectories: bool,
           out: str | None, db: str | None, config_path: str) -> None:
    """Export 5-minute periods, loop events, vehicles or health events from the store (read-only).

    Times select period_start (periods), wall_on (loop events), wall_exit (vehicles) or the
    event time (health; --lane does not apply).

    \b
    Examples:
      roadwatch export --from 2026-01-01T00:00Z --to 2026-01-02T00:00Z --csv -o day.csv
      roadwatch export --from 1767225600 --to 1767229200 --what loop-events --lane 1 --json
    """
    t_to = time.time() if t_to is None else t_to
    if t_to <= t_from:
        raise click.BadParameter(f"--to ({iso(t_to)}) must be after --from ({iso(t_from)})", param_hint="--to")
    store = open_readonly(store_path(db, config_path))
    try:
        rows = fetch(store, what, t_from, t_to, lane, trajectories)
    finally:
        store.close()
    text = json.dumps(rows, indent=1) + "\n" if fmt == "json" else to_csv(rows)
    if out:
        write_file(out, text)
        click.echo(f"wrote {len(rows)} {what} rows to {out}", err=True)
    else:
        sys.stdout.write(text)
        click.echo(f"{len(rows)} {what} rows {iso(t_from)} .. {iso(t_to)}", err=True)
