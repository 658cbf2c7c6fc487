"""The simulator's exact truth published to the Modbus TCP server and the serial line at once: what a
pymodbus client reads and what the line carries must equal the truth."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest
import serial
from pymodbus.client import ModbusTcpClient

from appliance import registers as rg
from appliance.config import load_site, parse_site
from appliance.types import ChannelState, DetectorSnapshot, LaneAggregate
from drivers.modbus_server import ModbusTcpOutput
from drivers.serial_line import SerialLineOutput, parse_sentence
from test_modbus_rtu import start_socat
from test_modbus_tcp import Sink

simulate = pytest.importorskip("tools.simulate.scenario")
truth_io = pytest.importorskip("tools.simulate.truth")

SECONDS, FPS = 30.0, 10.0


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    out = simulate.render_scenario("free-flow", 4, SECONDS, tmp_path_factory.mktemp("sim"), width=320, height=240,
                                   fps=FPS)
    events = truth_io.read_loop_events(out.truth_dir / "loop_events.csv")
    aggs = [LaneAggregate(**d) for d in truth_io.read_aggregates(out.truth_dir / "aggregates.csv")]
    return out, events, aggs


def truth_channels(site, events, t: float) -> list[ChannelState]:
    """Channel states a perfect detector shows at time t: presence call, count at loop entry."""
    out = []
    for lp in sorted(site.loops, key=lambda lp: lp.channel):
        evs = [e for e in events if e.channel == lp.channel]
        done = [e for e in evs if e.t_off <= t]
        out.append(ChannelState(
            lp.channel, lp.id, lp.lane, call=any(e.t_on <= t < e.t_off for e in evs),
            count=sum(1 for e in evs if e.t_on <= t), occupancy_pct=0.0,
            last_speed_kmh=done[-1].speed_kmh if done else None, last_length_m=done[-1].length_m if done else None))
    return out


@pytest.mark.skipif(shutil.which("socat") is None, reason="socat not installed")
def test_truth_over_modbus_and_serial_line(scenario, port):
    out, events, aggs = scenario
    assert len(events) >= 8 and aggs  # free-flow, 2 lanes at 700 veh/h each over 30 s
    proc, a, b = start_socat()
    raw = load_site(out.site).raw
    raw["outputs"] = {"modbus_tcp": {"enabled": True, "host": "127.0.0.1", "port": port},
                      "serial": {"enabled": True, "port": a, "baudrate": 115200}}
    site = parse_site(raw, "truth-site")
    outputs = [ModbusTcpOutput(site), SerialLineOutput(site)]
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3)
    try:
        with serial.Serial(b, 115200, timeout=0.2) as reader:
            for o in outputs:
                o.start(Sink())
            assert client.connect()
            wall0 = events[0].wall_on - events[0].t_on
            n_ch = len(site.loops)
            published, frames_with_call = 0, 0
            for i in range(int(SECONDS * FPS) + 1):
                t = i / FPS
                chans = truth_channels(site, events, t)
                done = [e for e in events if t - 1 / FPS < e.t_off <= t]
                snap = DetectorSnapshot(wall=wall0 + t, uptime_s=t, channels=chans, faults=0, fps=FPS,
                                        last_period=[], period_seq=0)
                for o in outputs:
                    o.publish(snap, done)
                published += len(done)
                bits = client.read_discrete_inputs(0, count=n_ch, device_id=1).bits[:n_ch]
                assert bits == [c.call for c in chans], t
                frames_with_call += any(bits)
                counts = client.read_input_registers(rg.CH_COUNT, count=n_ch, device_id=1).registers
                assert counts == [c.count for c in chans], t
                speeds = client.read_input_registers(rg.CH_SPEED, count=n_ch, device_id=1).registers
                assert speeds == [rg.NO_DATA if c.last_speed_kmh is None else round(c.last_speed_kmh * 10)
                                  for c in chans]
            # the period ends: the truth aggregates become the last complete period
            snap = DetectorSnapshot(wall=wall0 + SECONDS, uptime_s=SECONDS, channels=chans, faults=0, fps=FPS,
                                    last_period=aggs, period_seq=1)
            for o in outputs:
                o.publish(snap, [])
            block = client.read_input_registers(rg.PERIOD, count=6, device_id=1).registers
            assert block[:2] == [1, 300] and (block[2] << 16 | block[3]) == int(aggs[0].period_start)
            lanes = client.read_input_registers(rg.LANES, count=len(aggs) * rg.LANE_STRIDE, device_id=1).registers
            for slot, agg in enumerate(sorted(aggs, key=lambda a: a.lane)):
                rec = lanes[slot * rg.LANE_STRIDE : (slot + 1) * rg.LANE_STRIDE]
                assert rec[:4] == [agg.lane, agg.count, round(agg.occupancy_pct * 10), round(agg.speed_kmh * 10)]
                assert rec[5] == round(agg.flow_vph) and rec[10] == int(agg.partial)
            time.sleep(0.3)
            lines = []
            while raw_line := reader.readline():
                lines.append(parse_sentence(raw_line.decode("ascii")))
    finally:
        client.close()
        for o in outputs:
            o.stop()
        proc.kill()
        proc.wait(5)
    assert 10 <= frames_with_call < SECONDS * FPS  # calls went on and off during the run
    act = [f for f in lines if f[0] == "RWACT"]
    in_run = [e for e in events if e.t_off <= SECONDS]
    assert published == len(in_run) and len(act) == len(in_run)
    assert [(int(f[2]), f[4]) for f in act] == [(e.channel, e.loop_id) for e in sorted(in_run, key=lambda e: e.t_off)]
    assert np.allclose([float(f[6]) for f in act], [e.speed_kmh for e in sorted(in_run, key=lambda e: e.t_off)], atol=0.05)
    per = [f for f in lines if f[0] == "RWPER"]
    assert [(int(f[4]), int(f[5])) for f in per] == [(a.lane, a.count) for a in sorted(aggs, key=lambda a: a.lane)]
