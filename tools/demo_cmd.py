"""`roadwatch demo`: the real service on the embedded demo site and the synthetic live source,
with a live per-lane table on the terminal."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import click

from appliance.config import ConfigError, load_demo
from appliance.service import Service
from tools.service_cmd import serve, setup_logging, with_overrides


def lane_table(service: Service) -> str:
    """The live per-lane table: period count so far, total count, last speed, channel calls."""
    st = service.status()
    head = (f"t={st['uptime_s']:6.0f}s  fps {st['fps']:5.1f}  tracked {st['tracked_vehicles']:3d}  "
            f"dropped {st['dropped_frames']}  period_seq {st['period_seq']}  faults: {','.join(st['faults']) or 'none'}")
    rows = [head, f"{'lane':>4} {'period':>6} {'total':>6} {'speed km/h':>10}  calls"]
    by_lane: dict[int, list[dict]] = {}
    for ch in st["channels"]:
        by_lane.setdefault(ch["lane"], []).append(ch)
    for lane in sorted({int(k) for k in st["lanes"]} | set(by_lane)):
        chans = by_lane.get(lane, [])
        total = max((c["count"] for c in chans), default=0)
        speeds = [c["last_speed_kmh"] for c in chans if c["last_speed_kmh"] is not None]
        speed = f"{speeds[0]:10.1f}" if speeds else f"{'-':>10}"
        calls = " ".join(f"ch{c['channel']}:{'ON' if c['call'] else '--'}" for c in chans)
        rows.append(f"{lane:>4} {st['lanes'].get(str(lane), 0):>6} {total:>6} {speed}  {calls}")
    return "\n".join(rows)


@click.command("demo")
@click.option("--seconds", type=float, default=None, help="Stop after this many seconds (default: until Ctrl-C).")
@click.option("--workdir", type=click.Path(file_okay=False), default=".", show_default=True,
              help="Where the SQLite file is written.")
@click.option("--period-s", type=int, default=None, help="Aggregation period (s), shorter for a quick look.")
@click.option("--every", type=float, default=3.0, show_default=True, help="Seconds between table prints.")
@click.option("--modbus-port", type=int, default=None, help="Modbus TCP port (default from the demo site, 5020).")
@click.option("--status-port", type=int, default=None, help="Status HTTP port (default 8765; 0 = any free port).")
@click.option("-v", "--verbose", is_flag=True)
def demo(seconds: float | None, workdir: str, period_s: int | None, every: float,
         modbus_port: int | None, status_port: int | None, verbose: bool) -> None:
    """Run the real service on the embedded demo site (no camera needed).

    Prints a live per-lane table, writes the SQLite store in --workdir and serves the
    controller outputs on loopback, until Ctrl-C or --seconds.
    """
    setup_logging(verbose)
    try:
        site = load_demo()
        overrides: dict[str, dict] = {}
        if period_s is not None:
            overrides["measures"] = {"period_s": period_s}
        if modbus_port is not None:
            overrides["outputs.modbus_tcp"] = {"port": modbus_port}
        if status_port is not None:
            overrides["status"] = {"port": status_port}
        if overrides:
            site = with_overrides(site, overrides)
    except ConfigError as e:
        raise click.ClickException(str(e))
    wd = Path(workdir)
    wd.mkdir(parents=True, exist_ok=True)
    store_path = str((wd / Path(site.store.path).name).resolve())
    click.echo(f"roadwatch demo: site {site.site.name!r}, source {site.source.url}, store {store_path}")
    if site.outputs.modbus_tcp.enabled:
        o = site.outputs.modbus_tcp
        click.echo(f"Modbus TCP on {o.host}:{o.port} unit {o.unit_id}")
    stop_printing = threading.Event()

    def printer(service: Service) -> None:
        while not stop_printing.wait(every):
            click.echo(lane_table(service))
            sys.stdout.flush()

    service = None
    started = time.monotonic()
    try:
        service = serve(site, seconds=seconds, store_path=store_path,
                        on_ready=lambda s: threading.Thread(target=printer, args=(s,), daemon=True).start())
    finally:
        stop_printing.set()
    if service is not None:
        click.echo(lane_table(service))
        click.echo(f"demo ran {time.monotonic() - started:.0f} s; {service.frames} frames; store {store_path}")
        sys.stdout.flush()
