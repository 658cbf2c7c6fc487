"""`roadwatch registers`: print the Modbus register map for a config, or regenerate docs/registers.md."""

from __future__ import annotations

from pathlib import Path

import click

from appliance import registers as rg
from appliance.config import ConfigError, load_demo, load_site


@click.command(name="registers")
@click.option("-c", "--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="Site config TOML (default: the embedded demo site).")
@click.option("--markdown", "as_markdown", is_flag=True,
              help="Print the generic map as Markdown (the content of docs/registers.md).")
@click.option("-o", "--output", type=click.Path(dir_okay=False, writable=True), default=None,
              help="Write to this file instead of stdout (e.g. docs/registers.md).")
@click.option("--bench-latency", "bench_n", type=click.IntRange(1, 100000), default=None, metavar="N",
              help="Instead: serve the map on a free loopback port and measure N times the latency from "
                   "publishing a call change to a Modbus TCP client reading it.")
def registers(config_path: str | None, as_markdown: bool, output: str | None, bench_n: int | None) -> None:
    """Print the Modbus register map: every address (0-based wire and 1-based), type, unit,
    scaling and meaning. Without --markdown, per-channel and per-lane entries are expanded
    for the channels and lanes of the config."""
    if bench_n:
        _bench(config_path, bench_n)
        return
    if as_markdown:
        text = rg.markdown()
    else:
        try:
            site = load_site(config_path) if config_path else load_demo()
        except ConfigError as e:
            raise click.ClickException(f"config: {e}") from None
        layout = rg.Layout.from_site(site)
        text = _table(site.site.name, layout, site)
    if output:
        Path(output).write_text(text, encoding="utf-8")
        click.echo(f"wrote {output}")
    else:
        click.echo(text, nl=False)


def _table(name: str, layout: rg.Layout, site) -> str:
    o = site.outputs
    lines = [
        f"Register map v{rg.MAP_VERSION} for site '{name}': channels {layout.channels}, lanes {layout.lanes}, "
        f"classes {layout.class_names}",
        f"TCP {o.modbus_tcp.host}:{o.modbus_tcp.port} unit {o.modbus_tcp.unit_id} "
        f"({'on' if o.modbus_tcp.enabled else 'off'}); RTU {o.modbus_rtu.port} {o.modbus_rtu.baudrate} "
        f"{o.modbus_rtu.bytesize}{o.modbus_rtu.parity}{o.modbus_rtu.stopbits} unit {o.modbus_rtu.unit_id} "
        f"({'on' if o.modbus_rtu.enabled else 'off'}); writes {'allowed' if o.allow_writes else 'refused (exception 01)'}; "
        "uint32 = high word first",
    ]
    rows = rg.describe(layout)
    cols = ["table", "address", "one_based", "name", "index", "type", "unit", "scale"]
    width = {c: max(len(c), *(len(r[c]) for r in rows)) for c in cols}
    lines.append("  ".join(c.ljust(width[c]) for c in cols) + "  meaning")
    for r in rows:
        lines.append("  ".join(r[c].ljust(width[c]) for c in cols) + "  " + r["meaning"])
    return "\n".join(lines) + "\n"


def _bench(config_path: str | None, n: int) -> None:
    import socket

    import numpy as np

    from drivers.modbus_server import ModbusTcpOutput, bench_call_latency
    import copy

    from appliance.config import parse_site

    try:
        site = load_site(config_path) if config_path else load_demo()
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        raw = copy.deepcopy(site.raw)
        raw.setdefault("outputs", {})["modbus_tcp"] = {"enabled": True, "host": "127.0.0.1", "port": port}
        site = parse_site(raw, site.path)
    except ConfigError as e:
        raise click.ClickException(f"config: {e}") from None
    if not site.loops:
        raise click.ClickException("config: loops: the latency bench needs at least one loop")
    out = ModbusTcpOutput(site)
    out.start(None)  # type: ignore[arg-type]  # no force-call writes in the bench
    try:
        lat = bench_call_latency(out, "127.0.0.1", port, n) * 1000.0
    finally:
        out.stop()
    click.echo(f"publish -> call bit readable over Modbus TCP (loopback), n={n}: "
               f"median {np.median(lat):.2f} ms, p95 {np.percentile(lat, 95):.2f} ms, max {lat.max():.2f} ms")
