"""RS-232 ASCII event line for data loggers: one checksummed line per completed loop actuation,
per lane per period summary, and per health change (format in docs/serial-line.md)."""

from __future__ import annotations

import logging
import queue
import threading
import time
from datetime import datetime, timezone

import serial

from appliance.config import SiteConfig
from appliance.types import CommandSink, DetectorSnapshot, LaneAggregate, LoopEvent

log = logging.getLogger(__name__)

QUEUE_LINES = 4096  # lines buffered while the line is slow (9600 baud ~ 15 lines/s)


def checksum(body: str) -> str:
    """NMEA-style checksum: XOR of all characters between '$' and '*', two uppercase hex digits."""
    x = 0
    for b in body.encode("ascii"):
        x ^= b
    return f"{x:02X}"


def sentence(fields: list[str]) -> str:
    body = ",".join(fields)
    return f"${body}*{checksum(body)}\r\n"


def parse_sentence(line: str) -> list[str]:
    """Fields of one line; raises ValueError naming what is wrong (for loggers and tests)."""
    line = line.rstrip("\r\n")
    if not line.startswith("$") or "*" not in line:
        raise ValueError(f"not a Roadwatch line (needs $...*CS): {line!r}")
    body, _, cs = line[1:].rpartition("*")
    if checksum(body) != cs.upper():
        raise ValueError(f"bad checksum {cs!r}, expected {checksum(body)}: {line!r}")
    return body.split(",")


def _iso(wall: float) -> str:
    dt = datetime.fromtimestamp(wall, tz=timezone.utc)
    return dt.strftime("%Y-%m-%dT%H:%M:%S.") + f"{dt.microsecond // 1000:03d}Z"


def _num(value: float | None, digits: int) -> str:
    return "" if value is None else f"{value:.{digits}f}"


def actuation_line(ev: LoopEvent) -> str:
    """$RWACT,<on UTC>,<channel>,<lane>,<loop id>,<on time s>,<speed km/h>,<length m>*CS"""
    return sentence(
        [
            "RWACT",
            _iso(ev.wall_on),
            str(ev.channel),
            str(ev.lane),
            ev.loop_id,
            f"{max(ev.t_off - ev.t_on, 0.0):.3f}",
            _num(ev.speed_kmh, 1),
            _num(ev.length_m, 1),
        ]
    )


def period_line(agg: LaneAggregate, seq: int) -> str:
    """$RWPER,<start UTC>,<period s>,<seq>,<lane>,<count>,<flow veh/h>,<occ %>,<speed km/h>,<fault bits hex>*CS"""
    return sentence(
        [
            "RWPER",
            _iso(agg.period_start),
            str(int(agg.period_s)),
            str(seq & 0xFF),
            str(agg.lane),
            str(agg.count),
            f"{agg.flow_vph:.0f}",
            _num(agg.occupancy_pct, 1),
            _num(agg.speed_kmh, 1),
            f"{agg.quality & 0xFFFF:04X}",
        ]
    )


def health_line(wall: float, faults: int) -> str:
    """$RWHLT,<UTC>,<fault bits hex>*CS"""
    return sentence(["RWHLT", _iso(wall), f"{faults & 0xFFFF:04X}"])


class SerialLineOutput:
    """Writes event lines to outputs.serial.port; publish() only queues (drops oldest when full)."""

    def __init__(self, site: SiteConfig):
        self.cfg = site.outputs.serial
        self._queue: queue.Queue[str | None] = queue.Queue(QUEUE_LINES)
        self._thread: threading.Thread | None = None
        self._port: serial.Serial | None = None
        self._last_seq: int | None = None
        self._last_faults: int | None = None
        self.dropped = 0
        self.written = 0

    def start(self, commands: CommandSink) -> None:
        try:
            self._port = serial.Serial(self.cfg.port, self.cfg.baudrate, timeout=0, write_timeout=2.0)
        except (serial.SerialException, ValueError) as e:
            raise RuntimeError(f"outputs.serial.port {self.cfg.port!r}: cannot open ({e})") from e
        self._thread = threading.Thread(target=self._writer, name="roadwatch-serial", daemon=True)
        self._thread.start()

    def publish(self, snapshot: DetectorSnapshot, events: list[LoopEvent]) -> None:
        for ev in events:
            self._put(actuation_line(ev))
        if self._last_faults != snapshot.faults:
            self._put(health_line(snapshot.wall, snapshot.faults))
            self._last_faults = snapshot.faults
        if snapshot.last_period and snapshot.period_seq != self._last_seq:
            if self._last_seq is not None:  # do not repeat the period already reported before a start
                for agg in sorted(snapshot.last_period, key=lambda a: a.lane):
                    self._put(period_line(agg, snapshot.period_seq))
            self._last_seq = snapshot.period_seq
        elif not snapshot.last_period and self._last_seq is None:
            self._last_seq = -1

    def _put(self, line: str) -> None:
        while True:
            try:
                self._queue.put_nowait(line)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def _writer(self) -> None:
        while True:
            line = self._queue.get()
            if line is None:
                return
            try:
                self._port.write(line.encode("ascii"))
                self.written += 1
            except (serial.SerialException, OSError) as e:
                self.dropped += 1
                log.warning("serial line %s: write failed: %s", self.cfg.port, e)
                time.sleep(1.0)

    def stop(self) -> None:
        if self._thread is not None:
            self._put(None)  # type: ignore[arg-type]
            self._thread.join(5.0)
            self._thread = None
        if self._port is not None:
            try:
                self._port.flush()
            except (serial.SerialException, OSError) as e:
                log.warning("serial line %s: flush on close failed, unsent lines lost: %s", self.cfg.port, e)
            self._port.close()
            self._port = None
