"""The SQLite store: schema/migration, idempotent upserts, read-only readers, retention, durability flags."""

from __future__ import annotations

import sqlite3

import pytest

from appliance.store import SCHEMA_VERSION, Store, StoreError, period_from_row
from appliance.types import LaneAggregate, LoopEvent, VehicleRecord

T0 = 1767225600.0


def _agg(lane: int, k: int, count: int, partial: bool = False) -> LaneAggregate:
    return LaneAggregate(lane=lane, period_start=T0 + 300 * k, period_s=300, count=count, flow_vph=12.0 * count,
                         density_vpkm=1.5, speed_kmh=50.0 + k, time_mean_speed_kmh=51.0, occupancy_pct=3.5,
                         speed85_kmh=60.0, headway_s=20.0, class_counts={"small": count}, partial=partial, quality=0)


def _event(i: int, loop: str = "L1") -> LoopEvent:
    return LoopEvent(loop_id=loop, channel=1, lane=1, t_on=i, t_off=i + 0.2, wall_on=T0 + i, wall_off=T0 + i + 0.2,
                     speed_kmh=50.0, length_m=4.5, vehicle_id=i)


def test_schema_is_created_versioned_and_in_wal_mode(tmp_path) -> None:
    st = Store(tmp_path / "s.sqlite")
    assert st.schema_version() == SCHEMA_VERSION
    assert st.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert {"periods", "loop_events", "vehicles", "health_events", "state", "meta"} <= set(st.db.table_names())
    cols = [r[1] for r in st.db.execute("PRAGMA table_info(periods)").fetchall()]
    assert cols[:3] == ["lane", "period_start", "period_s"] and "written_wall" in cols


def test_periods_upsert_is_idempotent_and_round_trips(tmp_path) -> None:
    st = Store(tmp_path / "s.sqlite")
    st.write_periods([_agg(1, 0, 5), _agg(2, 0, 7), _agg(1, 1, 3, partial=True)])
    st.write_periods([_agg(1, 1, 4)])  # the period rewritten after a restart, now complete
    st.write_periods([_agg(1, 0, 5)])  # the same period again after a crash: no second row
    rows = st.periods()
    assert [(r["lane"], r["period_start"] - T0, r["count"], r["partial"]) for r in rows] == [
        (1, 0, 5, False), (2, 0, 7, False), (1, 300, 4, False)]
    assert period_from_row(rows[0]) == _agg(1, 0, 5)
    assert [r["lane"] for r in st.periods(T0, T0 + 300)] == [1, 2]
    assert [r["count"] for r in st.periods(lane=2)] == [7]


def test_events_and_vehicles_are_not_duplicated_on_rewrite(tmp_path) -> None:
    st = Store(tmp_path / "s.sqlite")
    st.write_loop_events([_event(1), _event(2), _event(2, "L2")])
    st.write_loop_events([_event(2), _event(3)])
    assert [(e["loop_id"], e["wall_on"] - T0) for e in st.loop_events()] == [("L1", 1), ("L1", 2), ("L2", 2), ("L1", 3)]
    v = VehicleRecord(id=4, lane=1, wall_entry=T0, wall_exit=T0 + 3, speed_kmh=50, length_m=4.4, length_class="small",
                      trajectory=[(0.0, 1.0, 30.0), (1.0, 1.0, 16.0)])
    st.write_vehicles([v], trajectories=False)
    st.write_vehicles([v], trajectories=True)
    rows = st.vehicles()
    assert len(rows) == 1 and rows[0]["vehicle_id"] == 4 and rows[0]["trajectory"] is None
    v2 = VehicleRecord(id=5, lane=2, wall_entry=T0 + 1, wall_exit=T0 + 4, speed_kmh=40, length_m=9.0,
                       length_class="medium", trajectory=[(0.0, 1.0, 30.0)])
    st.write_vehicles([v2], trajectories=True)
    assert st.vehicles(lane=2)[0]["trajectory"] == [[0.0, 1.0, 30.0]]


def test_state_blob_and_health(tmp_path) -> None:
    st = Store(tmp_path / "s.sqlite")
    st.save_state("period_seq", 17)
    st.save_blob("checkpoint", b"\x00\x01binary")
    st.write_health(T0, "CAMERA_LOST", True, "no frames")
    st.close()
    st = Store(tmp_path / "s.sqlite")
    assert st.load_state("period_seq") == 17 and st.load_state("missing", "dflt") == "dflt"
    assert st.load_blob("checkpoint") == b"\x00\x01binary"
    assert st.health_events()[0]["fault"] == "CAMERA_LOST"


def test_readers_are_read_only(tmp_path) -> None:
    Store(tmp_path / "s.sqlite").write_periods([_agg(1, 0, 5)])
    ro = Store(tmp_path / "s.sqlite", readonly=True)
    assert ro.periods()[0]["count"] == 5
    with pytest.raises(sqlite3.OperationalError, match="readonly"):
        ro.write_periods([_agg(1, 1, 5)])
    with pytest.raises(StoreError, match="no such store"):
        Store(tmp_path / "absent.sqlite", readonly=True)


def test_old_schema_is_migrated_and_newer_refused(tmp_path) -> None:
    path = tmp_path / "old.sqlite"
    conn = sqlite3.connect(path)  # a version-0 file: no meta table, an unrelated table
    conn.execute("CREATE TABLE notes (x TEXT)")
    conn.commit()
    conn.close()
    st = Store(path)
    assert st.schema_version() == SCHEMA_VERSION and "notes" in st.db.table_names()
    st.db.execute("UPDATE meta SET value='99' WHERE key='schema_version'")
    st.db.conn.commit()
    st.close()
    with pytest.raises(StoreError, match="schema version 99"):
        Store(path)
    with pytest.raises(StoreError, match="not a database|file is not"):
        (tmp_path / "junk.sqlite").write_bytes(b"x" * 4096)
        Store(tmp_path / "junk.sqlite")


def test_prune_by_age_and_size(tmp_path) -> None:
    st = Store(tmp_path / "s.sqlite")
    st.write_periods([_agg(1, 0, 5), _agg(1, 1000, 5)])
    st.write_loop_events([_event(i) for i in range(3)])
    now = T0 + 300 * 1000 + 10
    st.prune(retention_days=2, max_mb=100, now=now)  # keeps only what is under 2 days old
    assert [r["period_start"] for r in st.periods()] == [T0 + 300 * 1000]
    assert st.loop_events() == []
    st.write_loop_events([_event(i) for i in range(6000)])
    before = st.size_mb()
    assert before > 0.4  # 6000 events are well over 0.4 MB, so the size limit below must act
    n = st.prune(retention_days=10000, max_mb=0.2, now=now)
    assert n > 0 and st.size_mb() <= 0.2
    assert len(st.loop_events()) < 6000
    assert len(st.periods()) == 1  # detail rows go first; periods are kept while possible


def test_disk_full_raises_a_clear_sqlite_error(tmp_path) -> None:
    st = Store(tmp_path / "s.sqlite")
    pages = st.db.execute("PRAGMA page_count").fetchone()[0]
    st.db.execute(f"PRAGMA max_page_count={pages}")
    with pytest.raises(sqlite3.OperationalError, match="full"):
        st.write_loop_events([_event(i) for i in range(5000)])
    from appliance.store import is_disk_full

    try:
        st.write_loop_events([_event(i) for i in range(5000)])
    except sqlite3.OperationalError as e:
        assert is_disk_full(e)
