"""The local SQLite store (WAL, via sqlite-utils): period aggregates, loop events, vehicles,
health events and the service's saved state; schema versioned and migrated on open."""

from __future__ import annotations

import json
import os
import sqlite3
import time
from pathlib import Path
from typing import Any, Iterable

import sqlite_utils

from appliance.types import LaneAggregate, LoopEvent, VehicleRecord

SCHEMA_VERSION = 1

PERIOD_COLUMNS = [
    "lane", "period_start", "period_s", "count", "flow_vph", "density_vpkm", "speed_kmh",
    "time_mean_speed_kmh", "occupancy_pct", "speed85_kmh", "headway_s", "class_counts",
    "partial", "quality", "written_wall",
]

# Each entry upgrades the schema from version i to i+1.
_MIGRATIONS: list[str] = [
    """
    CREATE TABLE IF NOT EXISTS periods (
        lane INTEGER NOT NULL, period_start REAL NOT NULL, period_s REAL, count INTEGER,
        flow_vph REAL, density_vpkm REAL, speed_kmh REAL, time_mean_speed_kmh REAL,
        occupancy_pct REAL, speed85_kmh REAL, headway_s REAL, class_counts TEXT,
        partial INTEGER, quality INTEGER, written_wall REAL,
        PRIMARY KEY (lane, period_start));
    CREATE TABLE IF NOT EXISTS loop_events (
        id INTEGER PRIMARY KEY, loop_id TEXT, channel INTEGER, lane INTEGER, vehicle_id INTEGER,
        t_on REAL, t_off REAL, wall_on REAL, wall_off REAL, speed_kmh REAL, length_m REAL);
    CREATE UNIQUE INDEX IF NOT EXISTS loop_events_key ON loop_events (loop_id, wall_on);
    CREATE TABLE IF NOT EXISTS vehicles (
        id INTEGER PRIMARY KEY AUTOINCREMENT, vehicle_id INTEGER, lane INTEGER, wall_entry REAL,
        wall_exit REAL, speed_kmh REAL, length_m REAL, length_class TEXT, lane_changes INTEGER,
        trajectory TEXT);
    CREATE UNIQUE INDEX IF NOT EXISTS vehicles_key ON vehicles (vehicle_id, wall_entry);
    CREATE INDEX IF NOT EXISTS vehicles_exit ON vehicles (wall_exit);
    CREATE TABLE IF NOT EXISTS health_events (
        id INTEGER PRIMARY KEY, wall REAL, fault TEXT, active INTEGER, detail TEXT);
    CREATE TABLE IF NOT EXISTS state (key TEXT PRIMARY KEY, value TEXT);
    CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
    """,
]


class StoreError(RuntimeError):
    """The store cannot be opened or written (names the file and the reason)."""


def is_disk_full(exc: BaseException) -> bool:
    text = str(exc).lower()
    return "full" in text or "no space" in text or "disk i/o" in text


class Store:
    """One SQLite file. Writers migrate the schema on open; readers open it read-only."""

    def __init__(self, path: str | os.PathLike, *, readonly: bool = False):
        self.path = Path(path)
        self.readonly = readonly
        try:
            if readonly:
                if not self.path.exists():
                    raise StoreError(f"{self.path}: no such store")
                conn = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, check_same_thread=False)
            else:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                conn = sqlite3.connect(str(self.path), check_same_thread=False, timeout=10.0)
                conn.execute("PRAGMA auto_vacuum=INCREMENTAL")
            self.db = sqlite_utils.Database(conn)
            if not readonly:
                self.db.enable_wal()
                conn.execute("PRAGMA synchronous=NORMAL")
                self._migrate()
            else:
                version = self.schema_version()
                if version > SCHEMA_VERSION:
                    raise StoreError(f"{self.path}: schema version {version} is newer than this software ({SCHEMA_VERSION})")
        except sqlite3.DatabaseError as e:
            raise StoreError(f"{self.path}: {e}") from None

    # -- schema ------------------------------------------------------------------------------

    def schema_version(self) -> int:
        if "meta" not in self.db.table_names():
            return 0
        row = self.db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        return int(row[0]) if row else 0

    def _migrate(self) -> None:
        version = self.schema_version()
        if version > SCHEMA_VERSION:
            raise StoreError(f"{self.path}: schema version {version} is newer than this software ({SCHEMA_VERSION})")
        conn = self.db.conn
        for v in range(version, SCHEMA_VERSION):
            conn.executescript(_MIGRATIONS[v])
            with conn:
                conn.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('schema_version', ?)", (str(v + 1),))

    def close(self) -> None:
        self.db.conn.close()

    # -- writes ------------------------------------------------------------------------------

    def write_periods(self, aggregates: Iterable[LaneAggregate], written_wall: float | None = None) -> int:
        """Upsert period aggregates on (lane, period_start), durably (synchronous=FULL)."""
        wall = time.time() if written_wall is None else written_wall
        rows = [_period_row(a, wall) for a in aggregates]
        if not rows:
            return 0
        conn = self.db.conn
        conn.execute("PRAGMA synchronous=FULL")
        try:
            with conn:
                conn.executemany(
                    f"INSERT OR REPLACE INTO periods ({','.join(PERIOD_COLUMNS)}) "
                    f"VALUES ({','.join('?' * len(PERIOD_COLUMNS))})",
                    [[r[c] for c in PERIOD_COLUMNS] for r in rows],
                )
        finally:
            conn.execute("PRAGMA synchronous=NORMAL")
        return len(rows)

    def write_loop_events(self, events: Iterable[LoopEvent]) -> int:
        """Insert loop events; an event already stored (same loop and on time) is skipped."""
        cols = ["loop_id", "channel", "lane", "vehicle_id", "t_on", "t_off", "wall_on", "wall_off", "speed_kmh", "length_m"]
        rows = [[getattr(e, c) for c in cols] for e in events]
        if not rows:
            return 0
        with self.db.conn:
            self.db.conn.executemany(
                f"INSERT OR IGNORE INTO loop_events ({','.join(cols)}) VALUES ({','.join('?' * len(cols))})", rows
            )
        return len(rows)

    def write_vehicles(self, vehicles: Iterable[VehicleRecord], trajectories: bool = False) -> int:
        """Insert vehicle summaries (trajectory JSON only when asked); duplicates are skipped."""
        rows = []
        for v in vehicles:
            traj = json.dumps([list(p) for p in v.trajectory[:2000]]) if trajectories and v.trajectory else None
            rows.append([v.id, v.lane, v.wall_entry, v.wall_exit, v.speed_kmh, v.length_m, v.length_class, v.lane_changes, traj])
        if not rows:
            return 0
        with self.db.conn:
            self.db.conn.executemany(
                "INSERT OR IGNORE INTO vehicles (vehicle_id, lane, wall_entry, wall_exit, speed_kmh, length_m,"
                " length_class, lane_changes, trajectory) VALUES (?,?,?,?,?,?,?,?,?)",
                rows,
            )
        return len(rows)

    def write_health(self, wall: float, fault: str, active: bool, detail: str = "") -> None:
        with self.db.conn:
            self.db.conn.execute(
                "INSERT INTO health_events (wall, fault, active, detail) VALUES (?,?,?,?)",
                (wall, fault, int(active), detail),
            )

    def save_state(self, key: str, value: Any) -> None:
        with self.db.conn:
            self.db.conn.execute("INSERT OR REPLACE INTO state (key, value) VALUES (?, ?)", (key, json.dumps(value)))

    def save_blob(self, key: str, data: bytes) -> None:
        """Binary state (e.g. a resume checkpoint) in the state table, durably."""
        conn = self.db.conn
        conn.execute("PRAGMA synchronous=FULL")
        try:
            with conn:
                conn.execute("INSERT OR REPLACE INTO state (key, value) VALUES (?, ?)", (key, sqlite3.Binary(data)))
        finally:
            conn.execute("PRAGMA synchronous=NORMAL")

    def load_blob(self, key: str) -> bytes | None:
        row = self.db.execute("SELECT value FROM state WHERE key=?", [key]).fetchone()
        return None if row is None or not isinstance(row[0], bytes) else bytes(row[0])

    def load_state(self, key: str, default: Any = None) -> Any:
        row = self.db.execute("SELECT value FROM state WHERE key=?", [key]).fetchone()
        return default if row is None else json.loads(row[0])

    # -- reads -------------------------------------------------------------------------------

    def _range(self, table: str, time_col: str, from_wall: float, to_wall: float,
               key_col: str, key: int | None, order: str) -> list[dict]:
        """Rows of table with from_wall <= time_col < to_wall (and key_col = key unless None), as dicts."""
        sql = f"SELECT * FROM {table} WHERE {time_col} >= ? AND {time_col} < ?"
        args: list[Any] = [_num(from_wall), _num(to_wall)]
        if key is not None:
            sql += f" AND {key_col} = ?"
            args.append(key)
        return [dict(r) for r in self._rows(f"{sql} ORDER BY {order}", args)]

    def periods(self, from_wall: float = float("-inf"), to_wall: float = float("inf"), lane: int | None = None) -> list[dict]:
        """Period rows with from_wall <= period_start < to_wall, ordered by start then lane."""
        rows = self._range("periods", "period_start", from_wall, to_wall, "lane", lane, "period_start, lane")
        for r in rows:
            r["class_counts"] = json.loads(r["class_counts"] or "{}")
            r["partial"] = bool(r["partial"])
        return rows

    def loop_events(self, from_wall: float = float("-inf"), to_wall: float = float("inf"), channel: int | None = None) -> list[dict]:
        """Loop events with from_wall <= wall_on < to_wall, in time order."""
        return self._range("loop_events", "wall_on", from_wall, to_wall, "channel", channel, "wall_on, id")

    def vehicles(self, from_wall: float = float("-inf"), to_wall: float = float("inf"), lane: int | None = None) -> list[dict]:
        """Vehicle rows with from_wall <= wall_exit < to_wall, in exit order (trajectory decoded or None)."""
        rows = self._range("vehicles", "wall_exit", from_wall, to_wall, "lane", lane, "wall_exit, id")
        for r in rows:
            r["trajectory"] = json.loads(r["trajectory"]) if r["trajectory"] else None
        return rows

    def health_events(self, from_wall: float = float("-inf"), to_wall: float = float("inf")) -> list[dict]:
        return [dict(r) for r in self._rows(
            "SELECT * FROM health_events WHERE wall >= ? AND wall < ? ORDER BY wall, id", [_num(from_wall), _num(to_wall)])]

    def _rows(self, sql: str, args: list) -> list[sqlite3.Row]:
        cur = self.db.conn.cursor()
        cur.row_factory = sqlite3.Row
        return cur.execute(sql, args).fetchall()

    # -- retention ---------------------------------------------------------------------------

    def size_mb(self) -> float:
        """Pages in use (not counting free pages or the WAL), in MB."""
        q = lambda pragma: self.db.execute(f"PRAGMA {pragma}").fetchone()[0]  # noqa: E731
        return (q("page_count") - q("freelist_count")) * q("page_size") / 1e6

    def prune(self, retention_days: float, max_mb: float, now: float | None = None) -> int:
        """Delete rows older than retention_days, then the oldest detail rows (events, vehicles,
        health), then the oldest periods, until the file is under max_mb. Returns rows deleted."""
        now = time.time() if now is None else now
        cutoff = now - retention_days * 86400.0
        conn = self.db.conn
        deleted = 0
        with conn:
            for table, col in (("loop_events", "wall_on"), ("vehicles", "wall_exit"), ("health_events", "wall"), ("periods", "period_start")):
                deleted += conn.execute(f"DELETE FROM {table} WHERE {col} < ?", (cutoff,)).rowcount
        for table, col in (("loop_events", "wall_on"), ("vehicles", "wall_exit"), ("health_events", "wall"), ("periods", "period_start")):
            while self.size_mb() > max_mb:
                n = conn.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0]
                if n == 0:
                    break
                chunk = max(1, n // 10)
                with conn:
                    deleted += conn.execute(
                        f"DELETE FROM {table} WHERE rowid IN (SELECT rowid FROM {table} ORDER BY {col} LIMIT ?)", (chunk,)
                    ).rowcount
        if deleted:
            conn.execute("PRAGMA incremental_vacuum")
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        return deleted


def _num(x: float) -> float:
    # SQLite has no infinity literal binding issue, but clamp for clarity.
    return max(min(x, 1e300), -1e300)


def _period_row(a: LaneAggregate, wall: float) -> dict:
    d = a.to_dict()
    d["class_counts"] = json.dumps(a.class_counts, sort_keys=True)
    d["partial"] = int(bool(a.partial))
    d["quality"] = int(a.quality)
    d["written_wall"] = wall
    return d


def period_from_row(row: dict) -> LaneAggregate:
    """A LaneAggregate from a periods row (as returned by Store.periods)."""
    fields = {k: row[k] for k in PERIOD_COLUMNS if k != "written_wall"}
    if isinstance(fields["class_counts"], str):
        fields["class_counts"] = json.loads(fields["class_counts"])
    fields["partial"] = bool(fields["partial"])
    return LaneAggregate(**fields)
