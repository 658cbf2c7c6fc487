"""Modbus TCP server on loopback, read by pymodbus clients and mbpoll while real measures run."""

from __future__ import annotations

import re
import shutil
import socket
import struct
import subprocess
import time

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from appliance import registers as rg
from appliance.measures import TrafficMeasures
from appliance.types import DetectorSnapshot, HealthFault, VehicleState
from drivers.modbus_server import ModbusTcpOutput, bench_call_latency
from test_modbus_registers import ch, make_site, snapshot

EPOCH = 1767225600.0
FPS = 5.0
# (lane, speed m/s, headway s, lengths cycled, phase s): lane 1 approaching from y=100, lane 2 receding from y=0
TRAFFIC = [(1, 20.0, 3.1, (4.5, 15.0), 0.3), (2, 15.0, 4.3, (1.8, 8.0), 1.1)]


def vehicles_at(t: float) -> list[VehicleState]:
    """Constant-speed vehicles: exact trajectories, the ground truth fed to TrafficMeasures."""
    out = []
    for lane, speed, headway, lengths, phase in TRAFFIC:
        for j in range(int((t - phase) // headway) - int(120 / speed / headway) - 2, int((t - phase) // headway) + 1):
            dt = t - (phase + j * headway)
            length = lengths[j % len(lengths)]
            if dt < 0 or dt * speed > 100.0 + length:
                continue
            if lane == 1:
                yf = 100.0 - speed * dt
                out.append(VehicleState(lane * 100000 + j, t, -2.5, yf, yf + length, 0.0, -speed, length, 6))
            else:
                yf = speed * dt
                out.append(VehicleState(lane * 100000 + j, t, 2.5, yf, yf - length, 0.0, speed, length, 6))
    return out


def traffic_snapshots(site, seconds: float, start_wall: float = EPOCH + 250.0, faults_at=None):
    """(snapshot, loop events) per frame from TrafficMeasures fed with the exact trajectories."""
    tm = TrafficMeasures(site)
    last_period, seq = [], 0
    for i in range(int(seconds * FPS) + 1):
        t = i / FPS
        upd = tm.step(t, start_wall + t, vehicles_at(t))
        if upd.periods:
            last_period, seq = upd.periods, (seq + 1) % 256
        faults = faults_at(t) if faults_at else 0
        snap = DetectorSnapshot(wall=start_wall + t, uptime_s=t, channels=tm.channels(), faults=faults, fps=FPS,
                                last_period=list(last_period), period_seq=seq)
        yield snap, upd.loop_events


@pytest.fixture
def tcp_server(port):
    outputs = []

    def start(**outputs_cfg):
        cfg = {"modbus_tcp": {"enabled": True, "host": "127.0.0.1", "port": port}, **outputs_cfg}
        out = ModbusTcpOutput(make_site(**cfg))
        sink = Sink()
        out.start(sink)
        outputs.append(out)
        return out, sink

    yield start
    for out in outputs:
        out.stop()


class Sink:
    """A CommandSink that records what the controller asked for."""

    def __init__(self):
        self.calls: list[tuple[int, float]] = []

    def force_call(self, channel: int, seconds: float) -> None:
        self.calls.append((channel, seconds))


def test_live_map_matches_published_measures(tcp_server, port):
    out, _ = tcp_server()
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    assert client.connect()
    rng = np.random.default_rng(5)
    sample = set(rng.choice(int(360 * FPS), 150, replace=False).tolist())
    calls_seen, events = set(), {1: 0, 2: 0, 3: 0}
    snap = None
    for i, (snap, evs) in enumerate(traffic_snapshots(make_site(), 360.0)):
        out.publish(snap, evs)
        for ev in evs:
            events[ev.channel] += 1
        if i not in sample:
            continue
        by_ch = {c.channel: c for c in snap.channels}
        bits = client.read_discrete_inputs(0, count=3, device_id=1).bits
        for c in (1, 2):  # presence channels (3 is a pulse channel)
            assert bits[c - 1] == by_ch[c].call, f"call of channel {c} at frame {i}"
            calls_seen.add((c, by_ch[c].call))
        counts = client.read_input_registers(rg.CH_COUNT, count=3, device_id=1).registers
        assert counts == [by_ch[c].count & 0xFFFF for c in (1, 2, 3)]
        occ = client.read_input_registers(rg.CH_OCC, count=3, device_id=1).registers
        assert occ == [round(by_ch[c].occupancy_pct * 10) for c in (1, 2, 3)]
        block = client.read_input_registers(rg.PERIOD, count=6, device_id=1).registers
        assert block[0] == snap.period_seq
        if snap.last_period:
            lanes = client.read_input_registers(rg.LANES, count=2 * rg.LANE_STRIDE, device_id=1).registers
            for slot, agg in enumerate(sorted(snap.last_period, key=lambda a: a.lane)):
                rec = lanes[slot * rg.LANE_STRIDE : (slot + 1) * rg.LANE_STRIDE]
                assert rec[:4] == [agg.lane, agg.count, round(agg.occupancy_pct * 10), round(agg.speed_kmh * 10)]
            assert block[1] == 300 and (block[2] << 16 | block[3]) == int(snap.last_period[0].period_start)
    assert calls_seen == {(1, True), (1, False), (2, True), (2, False)}
    # ground truth: lane 1 has a vehicle every 3.1 s, lane 2 every 4.3 s; over 360 s each loop saw them all
    # (+-1 for a vehicle on the loop at either end)
    counts = client.read_input_registers(rg.CH_COUNT, count=3, device_id=1).registers
    assert abs(counts[0] - 360 / 3.1) <= 1.5 and abs(counts[1] - 360 / 4.3) <= 1.5
    # counts go up at loop entry, events are emitted at exit: a vehicle on a loop at the end differs by 1
    assert all(0 <= a - b <= 1 for a, b in zip(counts, events.values())), (counts, events)
    assert snap.period_seq == 2  # periods ending at EPOCH+300 (partial) and EPOCH+600
    client.close()


def test_faults_reach_the_controller(tcp_server, port):
    out, _ = tcp_server()
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    assert client.connect()
    faults = 1 << HealthFault.CAMERA_LOST
    out.publish(snapshot([ch(1, True, 5, 30.0), ch(2, True, 6, 10.0)], faults=faults), [])
    fault_bits = client.read_discrete_inputs(rg.DI_FAULT, count=17, device_id=1).bits[:17]
    assert fault_bits[HealthFault.CAMERA_LOST] and fault_bits[16] and sum(fault_bits) == 2
    assert client.read_input_registers(rg.CH_OCC, count=2, device_id=1).registers == [rg.FAULT_FLAG | 212] * 2
    assert client.read_input_registers(1, count=1, device_id=1).registers == [faults]
    out.publish(snapshot([ch(1, False, 5, 30.0)]), [])
    assert client.read_input_registers(rg.CH_OCC, count=1, device_id=1).registers == [300]
    assert not any(client.read_discrete_inputs(rg.DI_FAULT, count=17, device_id=1).bits[:17])
    client.close()


def test_heartbeat_and_exceptions(tcp_server, port):
    out, _ = tcp_server()
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    assert client.connect()
    hb0 = client.read_input_registers(0, count=1, device_id=1).registers[0]
    time.sleep(2.2)
    hb1 = client.read_input_registers(0, count=1, device_id=1).registers[0]
    assert 2 <= (hb1 - hb0) % 65536 <= 3
    for fn, addr, count in [
        (client.read_input_registers, 16, 1),  # gap after the status block
        (client.read_input_registers, rg.table_size("ir") - 1, 2),  # runs past the end
        (client.read_input_registers, 60000, 1),
        (client.read_discrete_inputs, 300, 1),
        (client.read_holding_registers, 256, 1),
    ]:
        rr = fn(addr, count=count, device_id=1)
        assert rr.isError() and rr.exception_code == 2, (fn.__name__, addr)
    rr = client.read_coils(0, count=1, device_id=1)
    assert rr.isError() and rr.exception_code == 1
    rr = client.read_input_registers(0, count=1, device_id=9)  # another unit behind a gateway
    assert rr.isError() and rr.exception_code == 0x0B
    assert client.read_input_registers(rg.STATUS + 13, count=1, device_id=0).registers == [rg.MAP_VERSION]
    info = client.read_device_information(device_id=1).information  # FC 43/14, basic objects
    assert info[0] == b"Roadwatch" and info[2] == ".".join(map(str, rg.firmware_version())).encode()
    # over-long read (the pymodbus client refuses to build it, so raw bytes)
    with socket.create_connection(("127.0.0.1", port), timeout=3) as s:
        s.sendall(struct.pack(">HHHBBHH", 7, 0, 6, 1, 4, 0, 126))
        assert s.recv(64) == struct.pack(">HHHBBB", 7, 0, 3, 1, 0x84, 3)
    client.close()


def test_writes_refused_unless_allowed(tcp_server, port):
    out, sink = tcp_server()
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    assert client.connect()
    rr = client.write_register(0, 10, device_id=1)
    assert rr.isError() and rr.exception_code == 1
    rr = client.write_registers(0, [10, 10], device_id=1)
    assert rr.isError() and rr.exception_code == 1
    assert sink.calls == [] and client.read_holding_registers(0, count=3, device_id=1).registers == [0, 0, 0]
    client.close()


def test_force_call_writes_are_forwarded(tcp_server, port):
    out, sink = tcp_server(allow_writes=True, force_call_max_s=60.0)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    assert client.connect()
    assert not client.write_register(0, 30, device_id=1).isError()
    assert not client.write_registers(1, [1000, 5], device_id=1).isError()  # channel 2 clamped to 60 s
    assert sink.calls == [(1, 30.0), (2, 60.0), (3, 5.0)]
    left = client.read_holding_registers(0, count=3, device_id=1).registers
    assert 29 <= left[0] <= 30 and 59 <= left[1] <= 60 and 4 <= left[2] <= 5
    assert not client.write_register(0, 0, device_id=1).isError()  # cancel
    assert sink.calls[-1] == (1, 0.0) and client.read_holding_registers(0, count=1, device_id=1).registers == [0]
    rr = client.write_register(7, 10, device_id=1)  # channel 8 is not configured
    assert rr.isError() and rr.exception_code == 2 and len(sink.calls) == 4
    client.close()


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="mbpoll not installed")
def test_mbpoll_reads_the_map(tcp_server, port):
    out, _ = tcp_server()
    out.publish(snapshot([ch(1, True, 70000, 12.3, 55.5, 4.4), ch(2, False, 3), ch(3, False, 9)]), [])

    def mbpoll(*args):
        res = subprocess.run(["mbpoll", "-m", "tcp", "-p", str(port), "-a", "1", "-1", *args, "127.0.0.1"],
                             capture_output=True, text=True, timeout=20)
        return res.returncode, {int(a): int(v) for a, v in re.findall(r"^\[(\d+)\]:\s+(-?\d+)", res.stdout, re.M)}, res

    rc, regs, res = mbpoll("-t", "3", "-r", "1", "-c", "10")  # 1-based references 30001..30010
    assert rc == 0, res.stderr
    assert regs[6] == 70000 & 0xFFFF and regs[5] == 70000 >> 16 and regs[7] == 3  # uptime (high first), channels
    rc, regs, _ = mbpoll("-t", "3", "-r", str(rg.CH_COUNT + 1), "-c", "3")
    assert rc == 0 and [regs[rg.CH_COUNT + 1 + i] for i in range(3)] == [70000 & 0xFFFF, 3, 9]
    rc, bits, _ = mbpoll("-t", "1", "-r", "1", "-c", "3")
    assert rc == 0 and [bits[1], bits[2], bits[3]] == [1, 0, 0]
    rc, _, res = mbpoll("-t", "3", "-r", "17", "-c", "1")
    assert rc != 0 and "Illegal data address" in res.stdout + res.stderr


def test_call_latency_bench_runs(tcp_server, port):
    out, _ = tcp_server()
    lat = bench_call_latency(out, "127.0.0.1", port, 20)
    # timing is reported by the bench, not asserted; the bit must have appeared for every change
    assert len(lat) == 20 and np.all(np.isfinite(lat))


def test_port_in_use_is_a_clear_error(port):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", port))
        busy.listen()
        out = ModbusTcpOutput(make_site(modbus_tcp={"enabled": True, "host": "127.0.0.1", "port": port}))
        with pytest.raises(RuntimeError, match=rf"outputs.modbus_tcp: cannot serve on 127.0.0.1:{port}"):
            out.start(Sink())


def test_force_cancelled_elsewhere_reads_zero(tcp_server, port):
    out, sink = tcp_server(allow_writes=True)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    assert client.connect()
    assert not client.write_register(1, 100, device_id=1).isError()
    out.publish(snapshot([ch(2, True, forced=False)]), [])  # the service has not applied it yet
    assert client.read_holding_registers(1, count=1, device_id=1).registers[0] >= 99
    out.publish(snapshot([ch(2, True, forced=True)]), [])
    assert client.read_discrete_inputs(rg.DI_FORCED + 1, count=1, device_id=1).bits[0]
    time.sleep(1.1)
    out.publish(snapshot([ch(2, False, forced=False)]), [])  # cancelled by the local config tool
    assert client.read_holding_registers(1, count=1, device_id=1).registers == [0]
    client.close()


def test_call_goes_on_within_one_frame_of_loop_entry(tcp_server, port):
    """Entry-to-call latency, first part: the frame that shows the call is at most one frame period
    after the exact moment the vehicle front enters the loop (the Modbus part is bench_call_latency)."""
    out, _ = tcp_server()
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    assert client.connect()
    lane, speed, headway, _, phase = TRAFFIC[0]
    loop_far_edge = 30.0 + 1.8  # loop L1 spans y 30..31.8 in lane 1; approaching vehicles enter at 31.8
    prev, delays = False, []
    for snap, evs in traffic_snapshots(make_site(), 60.0, start_wall=EPOCH):
        out.publish(snap, evs)
        call = next(c.call for c in snap.channels if c.channel == 1)
        if call and not prev:
            assert client.read_discrete_inputs(0, count=1, device_id=1).bits[0]  # readable right after publish
            t = snap.uptime_s
            j = np.floor((t - phase - (100.0 - loop_far_edge) / speed) / headway)
            t_enter = phase + j * headway + (100.0 - loop_far_edge) / speed
            delays.append(t - t_enter)
        prev = call
    assert len(delays) >= 18  # 60 s / 3.1 s headway
    assert min(delays) >= -1e-9 and max(delays) <= 1.0 / FPS + 1e-9, delays
    client.close()


def test_coalesced_requests_are_all_answered(tcp_server, port):
    """Two or more requests in one TCP segment (a master's retry after a stall, or pipelining)."""
    out, _ = tcp_server()
    out.publish(snapshot([ch(1, True, 11), ch(2, False, 22), ch(3, False, 33)]), [])
    with socket.create_connection(("127.0.0.1", port), timeout=3) as s:
        reqs = b"".join(struct.pack(">HHHBBHH", tid, 0, 6, 1, 4, rg.CH_COUNT + tid - 1, 1) for tid in (1, 2, 3))
        s.sendall(reqs)
        want = {tid: struct.pack(">HHHBBBH", tid, 0, 5, 1, 4, 2, 11 * tid) for tid in (1, 2, 3)}
        buf, deadline = b"", time.monotonic() + 3
        while len(buf) < sum(map(len, want.values())) and time.monotonic() < deadline:
            buf += s.recv(256)
    got = {struct.unpack(">H", buf[i : i + 2])[0]: buf[i : i + 11] for i in range(0, len(buf), 11)}
    assert got == want
