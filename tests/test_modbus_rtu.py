"""Modbus RTU slave over a socat pty pair: the map read by a pymodbus serial master, silence for
other unit ids on the shared bus."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time

import pytest
import serial
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ModbusIOException
from pymodbus.framer import FramerRTU

from appliance import registers as rg
from drivers.modbus_server import ModbusRtuOutput
from test_modbus_registers import ch, make_site, snapshot
from test_modbus_tcp import Sink, traffic_snapshots

pytestmark = pytest.mark.skipif(shutil.which("socat") is None, reason="socat not installed")


def start_socat() -> tuple[subprocess.Popen, str, str]:
    """A connected pair of raw ptys (like a null-modem cable); returns (process, end A, end B)."""
    proc = subprocess.Popen(["socat", "-d", "-d", "pty,raw,echo=0", "pty,raw,echo=0"],
                            stderr=subprocess.PIPE, text=True)
    names: list[str] = []
    deadline = time.monotonic() + 10
    while len(names) < 2 and time.monotonic() < deadline:
        line = proc.stderr.readline()
        names += re.findall(r"PTY is (\S+)", line)
    if len(names) < 2:
        proc.kill()
        pytest.fail("socat did not report two ptys")
    while not all(os.path.exists(n) for n in names):
        time.sleep(0.01)
    return proc, names[0], names[1]


@pytest.fixture
def pty_pair():
    proc, a, b = start_socat()
    yield a, b
    proc.kill()
    proc.wait(5)


def rtu_frame(unit: int, pdu: bytes) -> bytes:
    frame = bytes([unit]) + pdu
    return frame + FramerRTU.compute_CRC(frame).to_bytes(2, "big")


@pytest.fixture
def rtu_server(pty_pair):
    # ptys refuse parity settings (EINVAL), so the bus here is 8N1; the parity option is passed through to pyserial
    a, b = pty_pair
    out = ModbusRtuOutput(make_site(modbus_rtu={"enabled": True, "port": a, "baudrate": 115200,
                                                  "parity": "N", "unit_id": 7},
                                    allow_writes=True))
    sink = Sink()
    out.start(sink)
    yield out, sink, b
    out.stop()


def test_rtu_map_matches_published_measures(rtu_server):
    out, sink, port = rtu_server
    client = ModbusSerialClient(port, baudrate=115200, parity="N", timeout=1, retries=1)
    assert client.connect()
    checked = 0
    for i, (snap, evs) in enumerate(traffic_snapshots(make_site(), 330.0)):
        out.publish(snap, evs)
        if i % 100:
            continue
        by_ch = {c.channel: c for c in snap.channels}
        rr = client.read_input_registers(rg.CH_COUNT, count=3, device_id=7)
        assert rr.registers == [by_ch[c].count & 0xFFFF for c in (1, 2, 3)]
        bits = client.read_discrete_inputs(0, count=2, device_id=7).bits
        assert bits[:2] == [by_ch[1].call, by_ch[2].call]
        assert client.read_input_registers(rg.PERIOD, count=1, device_id=7).registers == [snap.period_seq]
        checked += 1
    assert checked >= 16 and snap.period_seq == 1 and by_ch[1].count > 90
    lane = client.read_input_registers(rg.LANES, count=4, device_id=7).registers
    agg = min(snap.last_period, key=lambda a: a.lane)
    assert lane == [agg.lane, agg.count, round(agg.occupancy_pct * 10), round(agg.speed_kmh * 10)]
    rr = client.read_input_registers(16, count=1, device_id=7)
    assert rr.isError() and rr.exception_code == 2
    assert not client.write_register(2, 12, device_id=7).isError() and sink.calls == [(3, 12.0)]
    client.close()


def test_other_unit_ids_get_no_answer(rtu_server):
    out, sink, port = rtu_server
    out.publish(snapshot([ch(1, True, 42)]), [])
    with serial.Serial(port, 115200, timeout=0.4) as s:
        # a second slave (unit 8) on the bus: reads, a write, diagnostics echo, report server id, broadcast
        for unit, pdu in [(8, b"\x04\x03\xe8\x00\x01"), (8, b"\x06\x00\x00\x00\x05"), (8, b"\x08\x00\x00\x12\x34"),
                          (8, b"\x11"), (0, b"\x06\x00\x00\x00\x05"), (6, b"\x04\x00\x00\x00\x01")]:
            s.reset_input_buffer()
            s.write(rtu_frame(unit, pdu))
            assert s.read(64) == b"", f"unit {unit} {pdu.hex()} was answered"
        s.write(rtu_frame(7, b"\x04\x03\xe8\x00\x01"))
        assert s.read(7) == rtu_frame(7, b"\x04\x02\x00\x2a")
        s.write(rtu_frame(7, b"\x04\x00\x00\x00\x7e"))  # 126 registers: exception 03
        assert s.read(5) == rtu_frame(7, b"\x84\x03")
    assert sink.calls == []
    client = ModbusSerialClient(port, baudrate=115200, parity="N", timeout=0.5, retries=0)
    assert client.connect()
    with pytest.raises(ModbusIOException, match="No response"):  # the master times out
        client.read_input_registers(rg.CH_COUNT, count=1, device_id=8)
    assert client.read_input_registers(rg.CH_COUNT, count=1, device_id=7).registers == [42]
    client.close()


def test_tcp_and_rtu_at_once_through_build_outputs(pty_pair, port):
    from pymodbus.client import ModbusTcpClient

    from drivers.outputs import build_outputs

    a, b = pty_pair
    site = make_site(modbus_tcp={"enabled": True, "host": "127.0.0.1", "port": port},
                     modbus_rtu={"enabled": True, "port": a, "baudrate": 38400, "parity": "N", "unit_id": 3})
    for _ in range(2):  # stop releases the port and the pty: a second start works
        outs = build_outputs(site)
        assert sorted(type(o).__name__ for o in outs) == ["ModbusRtuOutput", "ModbusTcpOutput"]
        for o in outs:
            o.start(Sink())
        try:
            for o in outs:
                o.publish(snapshot([ch(1, True, 11), ch(2, False, 12)]), [])
            tcp = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
            rtu = ModbusSerialClient(b, baudrate=38400, parity="N", timeout=1, retries=1)
            assert tcp.connect() and rtu.connect()
            assert tcp.read_input_registers(rg.CH_COUNT, count=2, device_id=1).registers == [11, 12]
            assert rtu.read_input_registers(rg.CH_COUNT, count=2, device_id=3).registers == [11, 12]
            assert rtu.read_discrete_inputs(0, count=2, device_id=3).bits[:2] == [True, False]
            tcp.close()
            rtu.close()
        finally:
            for o in outs:
                o.stop()
