"""The RS-232 event line over a socat pty pair: lines per actuation, per period and per health
change, checksummed, equal to the events the measures produced."""

from __future__ import annotations

import shutil
import time

import pytest
import serial

from appliance.types import HealthFault, LoopEvent
from drivers.serial_line import SerialLineOutput, actuation_line, checksum, parse_sentence, period_line
from test_modbus_registers import agg, make_site
from test_modbus_rtu import start_socat
from test_modbus_tcp import Sink, traffic_snapshots

EPOCH = 1767225600.0


def test_checksum_and_format():
    ev = LoopEvent("L1", 3, 2, 10.0, 10.4321, EPOCH + 0.25, EPOCH + 0.6821, 72.04, None)
    line = actuation_line(ev)
    assert line.endswith("\r\n") and line.isascii()
    assert parse_sentence(line) == ["RWACT", "2026-01-01T00:00:00.250Z", "3", "2", "L1", "0.432", "72.0", ""]
    body = line[1 : line.index("*")]
    x = 0
    for c in body:
        x ^= ord(c)
    assert line[line.index("*") + 1 : -2] == f"{x:02X}" == checksum(body)
    with pytest.raises(ValueError, match="bad checksum"):
        parse_sentence(line.replace("72.0", "73.0"))
    with pytest.raises(ValueError, match="not a Roadwatch line"):
        parse_sentence("RWACT,1,2\r\n")
    fields = parse_sentence(period_line(agg(2, count=7, occ=None, quality=1 << HealthFault.NO_HITS), 300))
    assert fields == ["RWPER", "2026-01-01T00:00:00.000Z", "300", "44", "2", "7", "84", "", "56.0", "0040"]


@pytest.mark.skipif(shutil.which("socat") is None, reason="socat not installed")
def test_event_line_over_pty_matches_measures():
    proc, a, b = start_socat()
    site = make_site(serial={"enabled": True, "port": a, "baudrate": 115200})
    out = SerialLineOutput(site)
    try:
        with serial.Serial(b, 115200, timeout=0.2) as reader:
            out.start(Sink())
            events, periods = [], []
            for snap, evs in traffic_snapshots(make_site(), 340.0,
                                               faults_at=lambda t: (1 << HealthFault.TOO_DARK) if 100 <= t < 110 else 0):
                out.publish(snap, evs)
                events += evs
                if snap.last_period and snap.last_period not in periods:
                    periods.append(snap.last_period)
            time.sleep(0.3)
            lines = []
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                raw = reader.readline()
                if not raw:
                    if len(lines) >= len(events):
                        break
                    continue
                lines.append(raw.decode("ascii"))
    finally:
        out.stop()
        proc.kill()
        proc.wait(5)
    parsed = [parse_sentence(line) for line in lines]  # every line carries a valid checksum
    act = [f for f in parsed if f[0] == "RWACT"]
    assert len(events) > 150 and len(act) == len(events)
    for f, ev in zip(act, events):
        assert (int(f[2]), int(f[3]), f[4]) == (ev.channel, ev.lane, ev.loop_id)
        assert float(f[5]) == pytest.approx(ev.t_off - ev.t_on, abs=1e-3)
        assert float(f[6]) == pytest.approx(ev.speed_kmh, abs=0.05)
    per = [f for f in parsed if f[0] == "RWPER"]
    assert len(periods) == 1 and [int(f[5]) for f in per] == [p.count for p in sorted(periods[0], key=lambda p: p.lane)]
    assert per[0][1] == "2026-01-01T00:00:00.000Z" and per[0][3] == "1"
    health = [f[2] for f in parsed if f[0] == "RWHLT"]
    assert health == ["0000", f"{1 << HealthFault.TOO_DARK:04X}", "0000"]
    assert out.dropped == 0


def test_unopenable_port_names_the_key(tmp_path):
    out = SerialLineOutput(make_site(serial={"enabled": True, "port": str(tmp_path / "no-such-tty")}))
    with pytest.raises(RuntimeError, match="outputs.serial.port"):
        out.start(Sink())


def test_doc_examples_carry_valid_checksums():
    from pathlib import Path

    doc = (Path(__file__).resolve().parent.parent / "docs" / "serial-line.md").read_text(encoding="utf-8")
    examples = [line for line in doc.splitlines() if line.startswith("$RW")]
    assert len(examples) == 3
    assert {parse_sentence(line)[0] for line in examples} == {"RWACT", "RWPER", "RWHLT"}
