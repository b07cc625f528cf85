"""OPC UA backend: the box's signals as nodes, and the client the daemon uses (asyncua).

Equal to the Modbus TCP backend (:mod:`.modbus`): the same signals, heartbeat, status bits and
raw-signal mode, for labs whose PLC or I/O system speaks OPC UA. asyncua is optional (extra
``opcua``) and imported only when this backend is used. asyncua is asynchronous: the client runs
in an event loop of its own (a thread per connection) and the daemon's calls wait for it with a
timeout, so a silent server costs at most ``timeout_s`` per call.

Address space (namespace URI ``namespace``, default ``urn:hvac-mpc:box``; string node ids)::

  HvacBox.Sensors.time_s                Double  read    sample time of the I/O side (s)
  HvacBox.Sensors.<sensor>              Double  read    supply_temp_c, volume_flow_m3s, hvac_inlet_temp_c,
                                                        water_temp_c, chiller_setpoint_c, heater_power_w,
                                                        heater_outlet_temp_c (units in the names); a bad
                                                        status code = no value, NaN = a bad reading
  HvacBox.Actuators.<input>             Double  write   blower_power_w, heater_cmd_w, valve_a/m/f/w_pct
  HvacBox.RawSignals.<input>            Double  write   the same actuators as raw device signals
                                                        (signals = "raw", units of the calibration)
  HvacBox.Watchdog.heartbeat            UInt16  write   sample counter (mod 65536), written every tick
  HvacBox.Watchdog.heartbeat_echo       UInt16  read    last heartbeat the device applied
  HvacBox.Watchdog.status               UInt16  read    bits as the Modbus status register
  HvacBox.Watchdog.signals              String  read    "engineering" or "raw": what the device takes

Each tick is two requests: one Read of the sensors and watchdog nodes, one Write of the six
actuators and the heartbeat together (the device applies them as one command). The device-side
heartbeat watchdog is the same as for Modbus (docs/fieldbus.md). Security: the client connects
with security mode None; keep the link on the lab's isolated network (or loopback).
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from typing import Any, Callable, Coroutine, Literal

from pydantic import BaseModel, ConfigDict, Field

from hvac_mpc.contract import INPUTS, Command, Measurement

from .calibration import Calibration
from .io import BackendError

SENSOR_NODES = ("time_s", "supply_temp_c", "volume_flow_m3s", "hvac_inlet_temp_c", "water_temp_c",
                "chiller_setpoint_c", "heater_power_w", "heater_outlet_temp_c")
ROOT = "HvacBox"


class OpcUaConfig(BaseModel):
    """``[backend.opcua]``: the OPC UA server (PLC, I/O system or :mod:`.opcua_sim`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    endpoint: str = Field("opc.tcp://127.0.0.1:4840/hvac-mpc/", pattern=r"^opc\.tcp://",
                          description="server endpoint URL")
    namespace: str = Field("urn:hvac-mpc:box", min_length=1, description="namespace URI of the box's nodes")
    timeout_s: float = Field(0.5, ge=0.01, le=10.0, allow_inf_nan=False, description="per request")
    signals: Literal["engineering", "raw"] = Field("engineering", description="actuator nodes written: "
                                                   "engineering values or raw device signals (calibration)")


def node_id(*path: str) -> str:
    """String identifier of a node, e.g. ``node_id("Sensors", "supply_temp_c")``."""
    return ".".join((ROOT,) + path)


def _asyncua():
    try:
        import asyncua
    except ImportError as exc:
        raise RuntimeError("the OPC UA backend needs asyncua: pip install 'hvac-mpc[opcua]'") from exc
    for name in ("asyncua", "asyncua.client", "asyncua.server", "asyncua.uaprotocol"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    return asyncua


class EventLoopThread:
    """An asyncio event loop in a daemon thread; ``run(coro, timeout_s)`` waits for a result."""

    def __init__(self, name: str):
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)
        self._thread.start()

    def run(self, coro: Coroutine, timeout_s: float) -> Any:
        fut = asyncio.run_coroutine_threadsafe(coro, self.loop)
        try:
            return fut.result(timeout_s)
        except BaseException:
            fut.cancel()
            raise

    def stop(self) -> None:
        """Cancel what still runs in the loop (the client's keep-alive), then end the thread."""
        async def cancel_all() -> None:
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for t in tasks:
                t.cancel()
            if tasks:
                await asyncio.wait(tasks, timeout=1.0)

        try:
            self.run(cancel_all(), 2.0)
        except BaseException:  # noqa: BLE001 - stopping anyway
            pass
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(2.0)
        if not self._thread.is_alive():
            self.loop.close()


class OpcUaBackend:
    """Daemon side of the address space above (asyncua client in its own event-loop thread)."""

    def __init__(self, cfg: OpcUaConfig, dt_s: float = 1.0, clock: Callable[[], float] | None = None,
                 calibration: Calibration | None = None):
        self.cfg, self.dt_s = cfg, dt_s
        self.clock = clock or (lambda: 0.0)
        self.calibration = calibration
        self._io: EventLoopThread | None = None
        self._client = None
        self._read_ids: list = []
        self._write_ids: list = []
        self.status_bits = 0
        self.heartbeat_echo = 0
        self.latency_s: list[float] = []  # wall time of recent read + write pairs (bounded)
        self._t_read = 0.0

    def _where(self) -> str:
        return f"OPC UA {self.cfg.endpoint}"

    def _call(self, what: str, coro: Coroutine, timeout_s: float) -> Any:
        if self._io is None:
            coro.close()
            raise BackendError(f"{self._where()}: not connected")
        try:
            return self._io.run(coro, timeout_s)
        except BackendError:
            self.close()
            raise
        except Exception as exc:  # noqa: BLE001 - any failure of the link is a backend error
            self.close()
            reason = "timed out" if isinstance(exc, (TimeoutError, asyncio.TimeoutError)) else repr(exc)
            raise BackendError(f"{self._where()}: {what} failed ({reason})") from None

    def connect(self) -> None:
        ua_mod = _asyncua()
        self.close()
        self._io = EventLoopThread("opcua-client")
        # the handshake is several round trips (hello, channel, session, activation, namespace)
        self._call("connect", self._connect(ua_mod), 8 * self.cfg.timeout_s + 1.0)

    async def _connect(self, ua_mod) -> None:
        ua = ua_mod.ua
        client = ua_mod.Client(self.cfg.endpoint, timeout=self.cfg.timeout_s)
        client.session_timeout = 30_000  # ms: the server drops a session of a daemon that died
        try:
            await client.connect()
            idx = await client.get_namespace_index(self.cfg.namespace)
            signals = await client.get_node(ua.NodeId(node_id("Watchdog", "signals"), idx)).read_value()
        except BaseException:
            try:
                await asyncio.wait_for(client.disconnect(), self.cfg.timeout_s)
            except BaseException:  # noqa: BLE001 - the link is gone anyway
                pass
            raise
        want = "raw" if self.calibration is not None else "engineering"
        if signals != want:
            await asyncio.wait_for(client.disconnect(), self.cfg.timeout_s)
            raise BackendError(f"{self._where()}: the device takes {signals} signals, the daemon is set to "
                               f"{want} (backend.opcua.signals)")
        folder = "RawSignals" if self.calibration is not None else "Actuators"
        self._read_ids = [ua.NodeId(node_id("Sensors", n), idx) for n in SENSOR_NODES] + [
            ua.NodeId(node_id("Watchdog", n), idx) for n in ("heartbeat_echo", "status")]
        self._write_ids = [ua.NodeId(node_id(folder, n), idx) for n in INPUTS] + [
            ua.NodeId(node_id("Watchdog", "heartbeat"), idx)]
        self._client = client

    def read(self) -> Measurement:
        if self._client is None:
            raise BackendError(f"{self._where()}: not connected")
        t0 = time.perf_counter()
        ua = _asyncua().ua
        dvs = self._call("read", self._client.uaclient.read_attributes(self._read_ids, ua.AttributeIds.Value),
                         self.cfg.timeout_s)
        self._t_read = time.perf_counter() - t0
        values = [_value(dv) for dv in dvs]
        n = len(SENSOR_NODES)
        self.heartbeat_echo = int(values[n] or 0)
        self.status_bits = int(values[n + 1] or 0)
        if values[0] is None or not math.isfinite(values[0]):
            raise BackendError(f"{self._where()}: no sample time ({values[0]!r})")
        m = Measurement(**dict(zip(SENSOR_NODES, values)))
        if self.calibration is not None:
            m = Measurement(time_s=m.time_s, **{k: self.calibration.sensor_to_eng(k, v)
                                                for k, v in m.as_dict().items() if k != "time_s"})
        return m

    def write(self, command: Command) -> None:
        if self._client is None:
            raise BackendError(f"{self._where()}: not connected")
        for name in INPUTS:
            if not math.isfinite(getattr(command, name)):
                raise ValueError(f"{name}: command must be finite, got {getattr(command, name)!r}")
        ua = _asyncua().ua
        t0 = time.perf_counter()
        if self.calibration is not None:
            raw = self.calibration.command_raw(command)
            values = [raw[n] for n in INPUTS]
        else:
            values = [float(getattr(command, n)) for n in INPUTS]
        heartbeat = (int(round(self.clock() / self.dt_s)) + 1) & 0xFFFF
        dvs = [ua.DataValue(ua.Variant(v, ua.VariantType.Double)) for v in values]
        dvs.append(ua.DataValue(ua.Variant(heartbeat, ua.VariantType.UInt16)))
        results = self._call("write", self._client.uaclient.write_attributes(self._write_ids, dvs,
                                                                              ua.AttributeIds.Value),
                             self.cfg.timeout_s)
        bad = [(i, r) for i, r in enumerate(results) if not r.is_good()]
        if bad:
            raise BackendError(f"{self._where()}: write refused for {[self._write_ids[i].Identifier for i, _ in bad]}"
                               f" ({bad[0][1]})")
        self.latency_s.append(self._t_read + time.perf_counter() - t0)
        if len(self.latency_s) > 10000:
            del self.latency_s[:5000]

    def close(self) -> None:
        """Close the session (bounded by ``timeout_s``) and end the client's event-loop thread."""
        client, self._client = self._client, None
        io, self._io = self._io, None
        if io is None:
            return
        if client is not None:
            try:
                io.run(asyncio.wait_for(client.disconnect(), self.cfg.timeout_s), 2 * self.cfg.timeout_s)
            except BaseException:  # noqa: BLE001 - closing a broken link may fail too
                pass
        io.stop()


def _value(dv) -> float | None:
    """A node's value; a bad status code or no value is None."""
    if dv.StatusCode is not None and not dv.StatusCode.is_good():
        return None
    v = dv.Value.Value if dv.Value is not None else None
    return None if v is None else float(v)
