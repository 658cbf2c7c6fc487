"""The register map as data and the pure snapshot encoding (no I/O), the generated doc, the CLI."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import tomli_w

from appliance import registers as rg
from appliance.config import parse_site
from appliance.types import ChannelState, DetectorSnapshot, HealthFault, LaneAggregate

REPO = Path(__file__).resolve().parent.parent
EPOCH = 1767225600.0


def site_dict(**outputs) -> dict:
    """A 2-lane site with a presence loop (channel 1), a pulse loop (channel 3) and channel 2."""
    return {
        "site": {"name": "modbus-test"},
        "source": {"width": 640, "height": 480, "fps": 25.0},
        "calibration": {
            "image_px": [[0, 479], [639, 479], [0, 0], [639, 0]],
            "road_m": [[-5, 0], [5, 0], [-5, 100], [5, 100]],
        },
        "lanes": [
            {"id": 1, "direction": "approaching", "polygon_m": [[-5, 0], [0, 0], [0, 100], [-5, 100]],
             "region_y_m": [20.0, 80.0], "count_y_m": 50.0},
            {"id": 2, "direction": "receding", "polygon_m": [[0, 0], [5, 0], [5, 100], [0, 100]],
             "region_y_m": [20.0, 80.0], "count_y_m": 40.0},
        ],
        "loops": [
            {"id": "L1", "lane": 1, "channel": 1, "y_m": 30.0, "length_m": 1.8},
            {"id": "L2", "lane": 2, "channel": 2, "y_m": 60.0, "length_m": 1.8},
            {"id": "L3", "lane": 2, "channel": 3, "y_m": 40.0, "length_m": 1.8, "mode": "pulse", "pulse_ms": 200},
        ],
        "outputs": outputs,
    }


def make_site(**outputs):
    return parse_site(site_dict(**outputs), "modbus-test")


def snapshot(channels, faults=0, last_period=(), seq=0, wall=EPOCH + 301.5, uptime=70000.4) -> DetectorSnapshot:
    return DetectorSnapshot(wall=wall, uptime_s=uptime, channels=list(channels), faults=faults, fps=24.96,
                            last_period=list(last_period), period_seq=seq, tracked_vehicles=3, dropped_frames=70001)


def ch(c, call=False, count=0, occ=0.0, speed=None, length=None, classes=None, forced=False) -> ChannelState:
    return ChannelState(c, f"L{c}", 1, call, count, occ, speed, length, classes or {}, forced)


def agg(lane, count=12, occ=8.46, speed=56.04, quality=0, classes=None) -> LaneAggregate:
    return LaneAggregate(lane, EPOCH, 300.0, count, count * 12.0, 3.21, speed, 57.0, occ, 70.0, 20.5,
                         classes or {"small": count}, False, quality)


def u32(ir, addr) -> int:
    return int(ir[addr]) << 16 | int(ir[addr + 1])


def test_map_fields_do_not_overlap_and_fit_5_digit_notation():
    for table in ("di", "ir", "hr"):
        owner = {}
        for f in rg.MAP:
            if f.table != table:
                continue
            for i in range(f.count):
                for a in range(f.addr(i), f.addr(i) + f.width):
                    assert a not in owner, f"{table} {a}: {f.name} overlaps {owner[a]}"
                    owner[a] = f.name
        assert max(owner) < 9999  # 30001+addr stays a 5-digit 3xxxx number
    assert rg.FIELDS["heartbeat"].address == 0 and rg.FIELDS["heartbeat"].table == "ir"


def test_encode_channels_status_and_scaling():
    layout = rg.Layout.from_site(make_site())
    snap = snapshot([ch(1, True, 70000, 12.34, 55.55, 4.44, {"small": 65537, "large": 2}), ch(2, count=5)])
    img = rg.encode_snapshot(snap, layout)
    assert img.di[rg.DI_CALL + 0] and not img.di[rg.DI_CALL + 1]
    assert img.ir[rg.CH_COUNT] == 70000 % 65536 and img.ir[rg.CH_COUNT + 1] == 5
    assert img.ir[rg.CH_OCC] == 123 and img.ir[rg.CH_SPEED] == 556 and img.ir[rg.CH_LENGTH] == 44
    assert img.ir[rg.CH_SPEED + 1] == rg.NO_DATA and img.ir[rg.CH_LENGTH + 1] == rg.NO_DATA
    small = layout.class_names.index("small")
    assert img.ir[rg.CH_CLASS + rg.CLASS_STRIDE * small] == 1
    assert img.ir[rg.CH_CLASS + rg.CLASS_STRIDE * layout.class_names.index("large")] == 2
    assert u32(img.ir, rg.FIELDS["uptime"].address) == 70000  # high word first
    assert u32(img.ir, rg.FIELDS["wall"].address) == int(EPOCH + 301.5)
    assert img.ir[rg.FIELDS["channels"].address] == 3 and img.ir[rg.FIELDS["max_channel"].address] == 3
    assert img.ir[rg.FIELDS["fps"].address] == 250
    assert img.ir[rg.FIELDS["dropped"].address] == 70001 % 65536
    assert img.ir[rg.FIELDS["health"].address] == 0 and not img.di[rg.DI_FAILSAFE]


def test_fault_bits_and_occupancy_fault_codes():
    layout = rg.Layout.from_site(make_site())
    faults = 1 << HealthFault.CAMERA_LOST | 1 << HealthFault.STORAGE
    img = rg.encode_snapshot(snapshot([ch(1, True, 3, 50.0)], faults=faults, last_period=[agg(1, quality=1 << HealthFault.NO_HITS), agg(2)]), layout)
    assert img.di[rg.DI_FAULT + HealthFault.CAMERA_LOST] and img.di[rg.DI_FAULT + HealthFault.STORAGE]
    assert not img.di[rg.DI_FAULT + HealthFault.TOO_DARK] and img.di[rg.DI_FAILSAFE]
    assert img.ir[rg.FIELDS["health"].address] == faults
    assert img.ir[rg.CH_OCC] == rg.FAULT_FLAG | 212
    lane1, lane2 = rg.LANES, rg.LANES + rg.LANE_STRIDE
    assert img.ir[lane1 + 2] == rg.FAULT_FLAG | 211 and img.ir[lane1 + 4] == 211
    assert img.ir[lane2 + 2] == 85 and img.ir[lane2 + 4] == 0
    # storage alone does not invalidate detector data
    img = rg.encode_snapshot(snapshot([ch(1, occ=50.0)], faults=1 << HealthFault.STORAGE), layout)
    assert img.ir[rg.CH_OCC] == 500 and not img.di[rg.DI_FAILSAFE]
    assert rg.fault_code(1 << HealthFault.NO_HITS | 1 << HealthFault.FROZEN_IMAGE) == 216  # priority order
    # no hits: data flagged (211) but the calls are not in fail-safe
    img = rg.encode_snapshot(snapshot([ch(1, occ=50.0)], faults=1 << HealthFault.NO_HITS), layout)
    assert img.ir[rg.CH_OCC] == rg.FAULT_FLAG | 211 and not img.di[rg.DI_FAILSAFE]


def test_failsafe_faults_match_the_service():
    from appliance.service import FAILSAFE_FAULTS

    assert set(rg.FAILSAFE_FAULTS) == set(FAILSAFE_FAULTS)
    assert all(rg.fault_code(1 << f) for f in FAILSAFE_FAULTS)  # a fail-safe always carries a fault code


def test_period_block():
    layout = rg.Layout.from_site(make_site())
    img = rg.encode_snapshot(snapshot([], last_period=[agg(2, count=7, speed=None, occ=None), agg(1)], seq=300), layout)
    assert img.ir[rg.PERIOD] == 300 % 256 and img.ir[rg.PERIOD + 1] == 300
    assert u32(img.ir, rg.PERIOD + 2) == int(EPOCH) and img.ir[rg.PERIOD + 4] == 2
    s0, s1 = rg.LANES, rg.LANES + rg.LANE_STRIDE  # slots sorted by lane id
    assert list(img.ir[s0 : s0 + 4]) == [1, 12, 85, 560]
    assert list(img.ir[s1 : s1 + 4]) == [2, 7, rg.NO_DATA, rg.NO_DATA]
    assert img.ir[s0 + 5] == 144 and img.ir[s0 + 9] == 205
    assert img.ir[s0 + 12 + layout.class_names.index("small")] == 12
    empty = rg.encode_snapshot(snapshot([]), layout)
    assert empty.ir[rg.PERIOD + 1] == 0 and empty.ir[s0 + 1] == rg.NO_DATA


def test_pulse_mode_gives_one_pulse_per_actuation():
    layout = rg.Layout.from_site(make_site())
    assert layout.pulse_s == {3: 0.2}
    shaper = rg.PulseShaper(layout)

    def step(now, call, forced=False, faults=0):
        img = rg.encode_snapshot(snapshot([ch(1, call), ch(3, call, forced=forced)], faults=faults), layout)
        shaper.update(img, now)
        return img

    img = step(10.0, True)
    assert shaper.calls(img, 10.0)[2] and shaper.calls(img, 10.19)[2] and not shaper.calls(img, 10.21)[2]
    assert shaper.calls(img, 10.5)[0]  # presence channel holds
    img = step(10.5, True)  # still present: no new pulse
    assert not shaper.calls(img, 10.5)[2]
    img = step(11.0, False)
    img = step(11.1, True)  # next vehicle
    assert shaper.calls(img, 11.2)[2] and not shaper.calls(img, 11.31)[2]
    img = step(12.0, True, forced=True)  # forced call is constant
    assert shaper.calls(img, 20.0)[2]
    img = step(21.0, True, faults=1 << HealthFault.CAMERA_LOST)  # fail-safe call is constant
    assert shaper.calls(img, 30.0)[2]
    img = step(31.0, False, faults=1 << HealthFault.NO_HITS)
    img = step(32.0, True, faults=1 << HealthFault.NO_HITS)  # not a fail-safe fault: still pulses
    assert shaper.calls(img, 32.1)[2] and not shaper.calls(img, 32.3)[2]


def test_docs_registers_md_is_generated_from_the_code():
    doc = REPO / "docs" / "registers.md"
    assert doc.read_text(encoding="utf-8") == rg.markdown(), "regenerate: roadwatch registers --markdown -o docs/registers.md"


def test_registers_command_prints_the_map_for_a_config(tmp_path):
    path = tmp_path / "site.toml"
    path.write_text(tomli_w.dumps(site_dict(allow_writes=True)), encoding="utf-8")
    res = subprocess.run([sys.executable, "-m", "tools.cli", "registers", "-c", str(path)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    rows = [line.split() for line in res.stdout.splitlines()[3:]]
    counts = [r for r in rows if r[3] == "count"]
    assert [(r[1], r[2], r[5]) for r in counts] == [("1000", "31001", "1"), ("1001", "31002", "2"), ("1002", "31003", "3")]
    assert "writes allowed" in res.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text('[outputs]\nallow_writes = "yes"\n', encoding="utf-8")
    res = subprocess.run([sys.executable, "-m", "tools.cli", "registers", "-c", str(bad)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode != 0 and "outputs.allow_writes" in res.stderr


def test_registers_command_latency_bench(tmp_path):
    path = tmp_path / "site.toml"
    path.write_text(tomli_w.dumps(site_dict()), encoding="utf-8")
    res = subprocess.run([sys.executable, "-m", "tools.cli", "registers", "-c", str(path), "--bench-latency", "20"],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert re.search(r"n=20: median [\d.]+ ms, p95 [\d.]+ ms, max [\d.]+ ms", res.stdout), res.stdout
