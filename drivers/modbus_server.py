"""Modbus TCP and RTU loop-detector outputs: pymodbus 3.16 servers in their own thread, serving
the register map of appliance/registers.py from the latest published snapshot."""

from __future__ import annotations

import asyncio
import logging
import threading
import time

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException, NoSuchIdException
from pymodbus.framer import FramerRTU, FramerType
from pymodbus.pdu import ExceptionResponse
from pymodbus.pdu.device import ModbusDeviceIdentification
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.transaction import TransactionManager

from appliance import registers as rg
from appliance.config import SiteConfig
from appliance.types import ChannelState, CommandSink, DetectorSnapshot, LoopEvent

log = logging.getLogger(__name__)

_READ_BITS = {2: "di"}
_READ_REGS = {4: "ir", 3: "hr", 6: "hr", 16: "hr", 23: "hr"}  # 6/16/23: read-back after a write
_WRITE_REGS = {6, 16, 23}


class RegisterStore:
    """The datastore both servers read: latest encoded image, heartbeat, force-call timers.

    ``publish`` runs in the frame-loop thread: it encodes the snapshot (~0.2 ms) and swaps the
    image reference; the async methods run in the server thread (pymodbus calls them as its
    context) and only read the current image."""

    def __init__(self, site: SiteConfig, unit_ids: set[int] | None = None):
        self.layout = rg.Layout.from_site(site)
        self.allow_writes = site.outputs.allow_writes
        self.force_max_s = float(site.outputs.force_call_max_s)
        self.unit_ids = unit_ids  # None: answer any unit id
        self.configured = np.zeros(rg.MAX_CHANNELS, dtype=bool)
        self.configured[[c - 1 for c in self.layout.channels]] = True
        self.masks = {t: rg.valid_mask(t) for t in ("di", "ir", "hr")}
        self.pulses = rg.PulseShaper(self.layout)
        self.image = rg.encode_snapshot(_empty_snapshot(), self.layout)
        self.heartbeat = 0
        self.force_until = np.zeros(rg.MAX_CHANNELS, dtype=np.float64)  # monotonic
        self.force_set = np.zeros(rg.MAX_CHANNELS, dtype=np.float64)  # when it was written
        self.commands: CommandSink | None = None
        self._lock = threading.Lock()

    # frame-loop side ---------------------------------------------------------------------
    def publish(self, snapshot: DetectorSnapshot) -> None:
        image = rg.encode_snapshot(snapshot, self.layout)
        now = time.monotonic()
        # a force cancelled elsewhere (status tool, reload) reads 0; allow the service a second to apply ours
        lapsed = (self.force_until > now) & ~image.di[rg.DI_FORCED : rg.DI_FORCED + rg.MAX_CHANNELS] & (now - self.force_set > 1.0)
        self.force_until[lapsed] = 0.0
        with self._lock:
            self.pulses.update(image, now)
            self.image = image

    # server side -------------------------------------------------------------------------
    def device_ids(self) -> list[int]:
        return sorted(self.unit_ids) if self.unit_ids else [0]

    def _check_unit(self, device_id: int) -> None:
        if self.unit_ids is not None and device_id not in self.unit_ids:
            raise NoSuchIdException(f"unit id {device_id} is not served here")

    def _in_map(self, table: str, address: int, count: int) -> bool:
        mask = self.masks[table]
        return 0 <= address and address + count <= len(mask) and bool(mask[address : address + count].all())

    def read(self, func_code: int, address: int, count: int) -> list[int] | list[bool] | ExcCodes:
        """Values for a read request, or the Modbus exception code."""
        if func_code in _READ_BITS:
            if not 1 <= count <= rg.MAX_READ_BITS:
                return ExcCodes.ILLEGAL_VALUE
            if not self._in_map("di", address, count):
                return ExcCodes.ILLEGAL_ADDRESS
            with self._lock:
                image = self.image
                calls = self.pulses.calls(image, time.monotonic())
            bits = image.di[address : address + count].copy()
            lo, hi = max(address, rg.DI_CALL), min(address + count, rg.DI_CALL + rg.MAX_CHANNELS)
            if lo < hi:
                bits[lo - address : hi - address] = calls[lo - rg.DI_CALL : hi - rg.DI_CALL]
            return [bool(b) for b in bits]
        if func_code in _READ_REGS:
            table = _READ_REGS[func_code]
            if not 1 <= count <= rg.MAX_READ_REGS:
                return ExcCodes.ILLEGAL_VALUE
            if not self._in_map(table, address, count):
                return ExcCodes.ILLEGAL_ADDRESS
            if table == "hr":
                left = np.ceil(np.maximum(self.force_until - time.monotonic(), 0.0))
                return [int(v) for v in np.minimum(left, 0xFFFF)[address : address + count]]
            words = self.image.ir[address : address + count].tolist()
            if address <= rg.STATUS < address + count:
                words[rg.STATUS - address] = self.heartbeat & 0xFFFF
            return words
        return ExcCodes.ILLEGAL_FUNCTION

    def write(self, func_code: int, address: int, values: list[int]) -> ExcCodes | None:
        """Apply a holding-register write (force call), or return the Modbus exception code."""
        if func_code not in _WRITE_REGS:
            return ExcCodes.ILLEGAL_FUNCTION
        if not self.allow_writes:
            return ExcCodes.ILLEGAL_FUNCTION
        if not 1 <= len(values) <= rg.MAX_WRITE_REGS:
            return ExcCodes.ILLEGAL_VALUE
        if not self._in_map("hr", address, len(values)):
            return ExcCodes.ILLEGAL_ADDRESS
        idx = np.arange(address, address + len(values)) - rg.HR_FORCE
        if not self.configured[idx].all():
            return ExcCodes.ILLEGAL_ADDRESS
        now = time.monotonic()
        for i, v in zip(idx, values):
            seconds = min(float(v), self.force_max_s)
            self.force_until[i] = now + seconds if seconds > 0 else 0.0
            self.force_set[i] = now
            if self.commands is not None:
                self.commands.force_call(int(i) + 1, seconds)
        return None

    # pymodbus context protocol
    async def async_getValues(self, device_id: int, func_code: int, address: int,
                              count: int = 1) -> list[int] | list[bool] | ExcCodes:
        self._check_unit(device_id)
        return self.read(func_code, address, count)

    async def async_setValues(self, device_id: int, func_code: int, address: int,
                              values: list[int] | list[bool]) -> ExcCodes | None:
        self._check_unit(device_id)
        return self.write(func_code, address, [int(v) for v in values])


def _empty_snapshot() -> DetectorSnapshot:
    return DetectorSnapshot(wall=0.0, uptime_s=0.0, channels=[], faults=0, fps=0.0, last_period=[], period_seq=0)


class _ModbusOutput:
    """Common part: one asyncio loop in a daemon thread running a server and the heartbeat."""

    name = "modbus"

    def __init__(self, site: SiteConfig):
        self.site = site
        self.store = RegisterStore(site, self._unit_ids())
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    def _unit_ids(self) -> set[int] | None:
        raise NotImplementedError

    def _make_server(self):
        raise NotImplementedError

    def where(self) -> str:
        raise NotImplementedError

    def start(self, commands: CommandSink) -> None:
        """Start serving in a background thread; returns once listening (raises if it cannot)."""
        self.store.commands = commands
        pm = logging.getLogger("pymodbus")
        if pm.level == logging.NOTSET:
            # pymodbus logs every malformed or foreign request at ERROR with a frame dump; on a
            # field bus that is line noise, not a detector fault (set a level to see it).
            pm.setLevel(logging.CRITICAL)
        self._started.clear()
        self._error = None
        self._thread = threading.Thread(target=self._run, name=f"roadwatch-{self.name.rsplit('.', 1)[-1]}", daemon=True)
        self._thread.start()
        if not self._started.wait(15.0):
            raise RuntimeError(f"{self.name}: server did not start within 15 s")
        if self._error is not None:
            raise RuntimeError(f"{self.name}: cannot serve on {self.where()}: {self._error}") from self._error

    def publish(self, snapshot: DetectorSnapshot, events: list[LoopEvent]) -> None:
        self.store.publish(snapshot)

    def stop(self) -> None:
        loop, server = self._loop, self._server
        if loop is not None and server is not None and loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(server.shutdown(), loop)
            try:
                fut.result(5.0)
            except Exception as e:  # noqa: BLE001 - shutting down anyway
                log.warning("%s: shutdown: %s", self.name, e)
        if self._thread is not None:
            self._thread.join(5.0)
        self._thread = None

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as e:  # noqa: BLE001 - reported to start()
            self._error = e
            self._started.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        server = self._make_server()
        server.context = self.store  # serve the live register image (see DESIGN.md pymodbus notes)
        self._server = server
        await server.serve_forever(background=True)  # raises when it cannot listen / open the port
        self._started.set()
        beat = asyncio.create_task(self._heartbeat())
        try:
            await server.serving
        finally:
            beat.cancel()

    async def _heartbeat(self) -> None:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        n = 0
        while True:
            n += 1
            await asyncio.sleep(max(t0 + n - loop.time(), 0.0))
            self.store.heartbeat = (self.store.heartbeat + 1) & 0xFFFF


class ModbusTcpOutput(_ModbusOutput):
    """Modbus TCP server on outputs.modbus_tcp.host:port; other unit ids get exception 0B."""

    name = "outputs.modbus_tcp"

    def _unit_ids(self) -> set[int]:
        return {self.site.outputs.modbus_tcp.unit_id, 0, 255}

    def where(self) -> str:
        cfg = self.site.outputs.modbus_tcp
        return f"{cfg.host}:{cfg.port}"

    def _make_server(self):
        cfg = self.site.outputs.modbus_tcp
        return _TcpServer(_placeholder(), framer=FramerType.SOCKET, address=(cfg.host, cfg.port),
                               identity=_identity(), trace_packet=_ExceptionFixer(rtu=False))


class ModbusRtuOutput(_ModbusOutput):
    """Modbus RTU slave on a serial port (RS-485/RS-232); silent for every other unit id."""

    name = "outputs.modbus_rtu"

    def _unit_ids(self) -> set[int]:
        return {self.site.outputs.modbus_rtu.unit_id}

    def where(self) -> str:
        return self.site.outputs.modbus_rtu.port

    def _make_server(self):
        cfg = self.site.outputs.modbus_rtu
        unit = cfg.unit_id

        def only_ours_in(sending: bool, pdu):
            # pymodbus answers diagnostics etc. for any id; drop requests for other slaves.
            return pdu if sending or pdu.dev_id == unit else None

        return _RtuServer(
            _placeholder(),
            framer=FramerType.RTU,
            identity=_identity(),
            port=cfg.port,
            baudrate=cfg.baudrate,
            parity=cfg.parity,
            stopbits=cfg.stopbits,
            bytesize=cfg.bytesize,
            ignore_missing_devices=True,
            trace_pdu=only_ours_in,
            trace_packet=_ExceptionFixer(rtu=True, unit=unit),
        )


class _ExceptionFixer:
    """Packet filter: pymodbus answers a request it cannot decode with function code 0x80; send the
    proper exception instead (request's function | 0x80; 01 for an unknown function, 03 for a
    known one with bad values, e.g. 126 registers). RTU: never send for another unit id."""

    KNOWN = frozenset({1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 15, 16, 17, 20, 21, 22, 23, 24, 43})

    def __init__(self, rtu: bool, unit: int | None = None):
        self.rtu, self.unit = rtu, unit
        self.fc_at = 1 if rtu else 7
        self.last_fc: int | None = None

    def __call__(self, sending: bool, packet: bytes) -> bytes:
        at = self.fc_at
        if not sending:
            self.last_fc = packet[at] if len(packet) > at else None
            return packet
        if self.rtu and packet[:1] != bytes([self.unit]):
            return b""
        fc = self.last_fc
        if len(packet) > at and packet[at] == 0x80 and fc is not None and 0 < fc < 0x80:
            code = ExcCodes.ILLEGAL_VALUE if fc in self.KNOWN else ExcCodes.ILLEGAL_FUNCTION
            packet = packet[:at] + bytes([0x80 | fc, int(code)])
            if self.rtu:
                packet += FramerRTU.compute_CRC(packet).to_bytes(2, "big")
        return packet


RTU_GAP_S = 0.05  # least silence that ends an RTU frame; generous for USB adapters that deliver in chunks


def rtu_gap_s(baudrate: int) -> float:
    """Silence after which a partial RTU frame is dropped: 50 ms, or 10 character times when slower."""
    return max(RTU_GAP_S, 10 * 11 / baudrate)


class _GapHandler(ServerRequestHandler):
    """RTU request handler that drops a stale partial frame after a silent interval, as the RTU
    3.5-character rule does (pymodbus keeps it and would glue the next request onto it)."""

    _last_rx = 0.0
    gap_s = RTU_GAP_S

    def data_received(self, data: bytes) -> None:
        now = time.monotonic()
        if self.recv_buffer and now - self._last_rx > self.gap_s:
            self.recv_buffer = b""
        self._last_rx = now
        super().data_received(data)


MAX_MBAP_LENGTH = 254  # unit id + PDU of the largest Modbus/TCP ADU (260 bytes)


class _TcpHandler(ServerRequestHandler):
    """Answers every complete request in a received chunk, each with its own PDU. pymodbus 3.16
    handles only the first and keeps the rest until more bytes arrive, which leaves a master whose
    requests were coalesced (a retry after a stall, or pipelining) one answer behind for good."""

    def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
        used = 0
        while used < len(data):
            rest = data[used:]
            if len(rest) >= 6 and (rest[2:4] != b"\0\0" or int.from_bytes(rest[4:6], "big") > MAX_MBAP_LENGTH):
                return len(data)  # not Modbus/TCP, or longer than any request: nothing after it can be framed
            try:
                n = TransactionManager.callback_data(self, rest, addr)
            except ModbusIOException as exc:  # undecodable request: exception 0x80, fixed by _ExceptionFixer
                response = ExceptionResponse(exc.fcode or 0, exception_code=ExcCodes.ILLEGAL_FUNCTION,
                                             device_id=exc.dev_id, transaction=exc.transaction_id)
                self.server_send(response, addr)
                used += 6 + int.from_bytes(rest[4:6], "big")  # skip just that request
                continue
            if not n:
                break
            used += n
            if self.last_pdu:
                asyncio.ensure_future(self._answer(self.last_pdu, self.last_addr))
        return min(used, len(data))

    def send(self, data: bytes, addr: tuple | None = None) -> None:
        kept = self.recv_buffer  # pymodbus clears it on send, losing a request that is arriving
        super().send(data, addr)
        self.recv_buffer = kept

    async def _answer(self, pdu, addr) -> None:
        try:
            response = await pdu.datastore_update(self.server.context, pdu.dev_id)
        except NoSuchIdException:
            response = ExceptionResponse(pdu.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
        except Exception as e:  # noqa: BLE001 - a bad request must not stop the server
            log.warning("modbus request %s failed: %s", pdu, e)
            response = ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)
        response.transaction_id = pdu.transaction_id
        response.dev_id = pdu.dev_id
        self.server_send(response, addr)


class _TcpServer(ModbusTcpServer):
    def callback_new_connection(self):
        return _TcpHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class _RtuServer(ModbusSerialServer):
    def callback_new_connection(self):
        handler = _GapHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)
        handler.gap_s = rtu_gap_s(self.comm_params.baudrate or 19200)
        return handler


def _identity() -> ModbusDeviceIdentification:
    """What FC 43/14 (read device identification) reports."""
    return ModbusDeviceIdentification(info_name={
        "VendorName": "Roadwatch",
        "ProductCode": "RW-VD",
        "MajorMinorRevision": ".".join(str(v) for v in rg.firmware_version()),
        "ProductName": "Roadwatch video vehicle detector",
        "ModelName": f"loop emulation, register map v{rg.MAP_VERSION}",
    })


def _placeholder() -> SimDevice:
    # pymodbus wants a datastore at construction; it is replaced by the RegisterStore.
    return SimDevice(0, simdata=[SimData(0, values=0, datatype=DataType.REGISTERS)])


def bench_call_latency(output: _ModbusOutput, host: str, port: int, n: int = 200) -> np.ndarray:
    """Seconds from publish() of a snapshot that toggles the first channel's call to a Modbus TCP
    client on (host, port) reading the new bit (the client polls as fast as it can)."""
    from pymodbus.client import ModbusTcpClient

    channels = output.store.layout.channels
    if not channels:
        raise ValueError("the site has no loops, so no call to measure")
    first = channels[0]
    client = ModbusTcpClient(host, port=port, timeout=3)
    if not client.connect():
        raise ConnectionError(f"cannot connect to {host}:{port}")
    unit = output.site.outputs.modbus_tcp.unit_id
    out = []
    try:
        for i in range(n):
            want = i % 2 == 0
            chans = [ChannelState(c, "", 0, want and c == first, i, 0.0, None, None) for c in channels]
            snap = DetectorSnapshot(wall=time.time(), uptime_s=float(i), channels=chans, faults=0, fps=0.0,
                                    last_period=[], period_seq=0)
            t0 = time.perf_counter()
            output.publish(snap, [])
            while client.read_discrete_inputs(rg.DI_CALL + first - 1, count=1, device_id=unit).bits[0] != want:
                if time.perf_counter() - t0 > 5.0:
                    raise TimeoutError("the call bit did not change within 5 s")
            out.append(time.perf_counter() - t0)
    finally:
        client.close()
    return np.asarray(out)


__all__ = ["ModbusRtuOutput", "ModbusTcpOutput", "RegisterStore", "bench_call_latency"]
