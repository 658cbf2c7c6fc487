"""`roadwatch selftest`: renders a short synthetic scene, runs it through this box's real
pipeline, store and Modbus output, and checks the results against the scene's exact truth."""

from __future__ import annotations

import csv
import logging
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

import click

from appliance.config import load_site
from appliance.service import Service
from tools.service_cmd import make_hooks, software_version, with_overrides

# Counting tolerance per lane: the feature tracker's documented counting accuracy on the
# free-flow preset is within a few percent; a box that works end to end stays well inside this.
COUNT_TOLERANCE = 0.25
COUNT_SLACK = 2


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _truth_counts(truth_dir: Path) -> dict[int, int]:
    out: dict[int, int] = {}
    with open(truth_dir / "aggregates.csv", newline="") as f:
        for row in csv.DictReader(f):
            out[int(row["lane"])] = out.get(int(row["lane"]), 0) + int(float(row["count"]))
    return out


def _read_modbus(port: int, channels: list[int]) -> dict:
    from pymodbus.client import ModbusTcpClient

    from appliance import registers as rg

    c = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    if not c.connect():
        raise RuntimeError(f"cannot connect to the Modbus TCP output on 127.0.0.1:{port}")
    try:
        seq = c.read_input_registers(rg.FIELDS["period_seq"].address, count=1, device_id=1)
        counts = {}
        for ch in channels:
            r = c.read_input_registers(rg.FIELDS["count"].addr(ch - 1), count=1, device_id=1)
            counts[ch] = None if r.isError() else r.registers[0]
        return {"period_seq": None if seq.isError() else seq.registers[0], "counts": counts}
    finally:
        c.close()


@click.command("selftest")
@click.option("--preset", default="free-flow", show_default=True, help="Synthetic scene to render.")
@click.option("--seed", default=7, show_default=True)
@click.option("--seconds", default=40.0, show_default=True, help="Length of the rendered scene.")
@click.option("--workdir", type=click.Path(file_okay=False), default=None, help="Keep the files here (default: a temp dir).")
@click.option("-v", "--verbose", is_flag=True)
def selftest(preset: str, seed: int, seconds: float, workdir: str | None, verbose: bool) -> None:
    """Prove this box works end to end: render → pipeline → store → Modbus, checked against truth."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="roadwatch-selftest-")
        workdir = tmp.name
    wd = Path(workdir)
    results: list[tuple[str, bool, str]] = []
    try:
        from tools.simulate import render_scenario

        t0 = time.monotonic()
        click.echo(f"roadwatch {software_version()} selftest: rendering {seconds:g} s of '{preset}' (seed {seed}) ...")
        out = render_scenario(preset, seed, seconds, wd / "scene", width=320, height=240)
        click.echo(f"  rendered {out.meta['frame_count']} frames in {time.monotonic() - t0:.1f} s")
        mb_port = _free_port()
        site = with_overrides(load_site(out.site), {
            "measures": {"period_s": 10},
            "store": {"path": str(wd / "selftest.sqlite")},
            "status": {"enabled": False},
            "outputs.modbus_tcp": {"enabled": True, "host": "127.0.0.1", "port": mb_port, "unit_id": 1},
        })
        seen: dict = {}

        def check_outputs(service: Service) -> None:
            snap = service.last_snapshot
            try:
                seen["modbus"] = _read_modbus(mb_port, [c.channel for c in snap.channels])
            except Exception as e:  # noqa: BLE001 - reported as a failed check
                seen["modbus_error"] = str(e)
            seen["snapshot"] = snap

        hooks = make_hooks(site)
        hooks.before_stop = check_outputs
        service = Service(site, hooks, version=software_version())
        t1 = time.monotonic()
        service.run()
        took = time.monotonic() - t1
        click.echo(f"  processed {service.frames} frames in {took:.1f} s ({service.frames / max(took, 1e-6):.0f} frame/s)")

        conn = sqlite3.connect(f"file:{wd / 'selftest.sqlite'}?mode=ro", uri=True)
        rows = conn.execute("SELECT lane, period_start, count, partial FROM periods ORDER BY period_start, lane").fetchall()
        complete = {r[1] for r in rows if not r[3]}
        expected = int((out.meta["frame_count"] - 1) / out.meta["fps"] // 10)
        results.append(("store: every complete period written once", len(complete) == expected and
                        len(rows) == len({(r[0], r[1]) for r in rows}), f"{len(complete)} complete periods, expected {expected}"))
        truth = _truth_counts(out.truth_dir)
        got: dict[int, int] = {}
        for lane, _, count, _ in rows:
            got[lane] = got.get(lane, 0) + count
        for lane in sorted(truth):
            t, g = truth[lane], got.get(lane, 0)
            ok = abs(g - t) <= max(COUNT_SLACK, COUNT_TOLERANCE * t)
            results.append((f"lane {lane} count vs truth", ok, f"{g} counted, {t} true"))
        if "modbus" in seen:
            mb, snap = seen["modbus"], seen["snapshot"]
            ok = mb["period_seq"] == snap.period_seq and all(
                mb["counts"][c.channel] == c.count % 65536 for c in snap.channels)
            results.append(("modbus: period sequence and channel counts", ok,
                            f"period_seq {mb['period_seq']} vs {snap.period_seq}, counts {mb['counts']}"))
        else:
            results.append(("modbus: period sequence and channel counts", False, seen.get("modbus_error", "not read")))
        faults = service.health.names()
        results.append(("health: no camera or processing fault", not {"CAMERA_LOST", "FROZEN_IMAGE", "TOO_DARK"} & set(faults),
                        ", ".join(faults) or "none"))
    except Exception as e:  # noqa: BLE001 - the selftest reports, it does not crash
        results.append(("selftest ran", False, f"{type(e).__name__}: {e}"))
    finally:
        if tmp is not None:
            tmp.cleanup()
    failed = 0
    for name, ok, detail in results:
        click.echo(f"  [{'PASS' if ok else 'FAIL'}] {name}: {detail}")
        failed += not ok
    click.echo("selftest " + ("PASSED" if not failed else f"FAILED ({failed} check(s))"))
    sys.exit(1 if failed else 0)
