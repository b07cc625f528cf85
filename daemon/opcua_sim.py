"""The simulated plant behind a real OPC UA server (asyncua; address space of :mod:`.opcua`).

The OPC UA counterpart of :mod:`.modbus_sim`, with the same plant side
(:class:`.device_sim.SimulatedDevice`: lockstep or realtime clock, I/O watchdog, heartbeat
watchdog, raw signals decoded with a calibration). Sensor nodes are computed from the plant on
every read; a write that includes the heartbeat node applies the actuator nodes as one command.
``sensor_override`` replaces readings (a number, NaN, or None for a bad status code) to test
the daemon's sensor checks. Run standalone::

    python -m hvac_mpc.daemon.opcua_sim --port 4840 --mode realtime
"""

from __future__ import annotations

import math

from hvac_mpc.contract import INPUTS, Command
from hvac_mpc.models.plant import SimulatedPlant

from .calibration import Calibration
from .device_sim import SimulatedDevice, run_standalone
from .opcua import SENSOR_NODES, _asyncua, node_id


class PlantOpcUaServer(SimulatedDevice):
    """An OPC UA server at ``opc.tcp://host:port/hvac-mpc/`` exposing ``plant``; start/stop it any
    number of times (the plant lives on between)."""

    name = "OPC UA"

    def __init__(self, plant: SimulatedPlant, host: str = "127.0.0.1", port: int = 4840,
                 namespace: str = "urn:hvac-mpc:box", mode: str = "lockstep", speedup: float = 1.0,
                 watchdog_samples: int = 5, max_catchup_samples: int = 3600, heartbeat_timeout_s: float = 3.0,
                 cooldown_blower_w: float = 120.0, calibration: Calibration | None = None):
        super().__init__(plant, mode=mode, speedup=speedup, watchdog_samples=watchdog_samples,
                         max_catchup_samples=max_catchup_samples, heartbeat_timeout_s=heartbeat_timeout_s,
                         cooldown_blower_w=cooldown_blower_w, calibration=calibration)
        self.host, self.port, self.namespace = host, port, namespace
        self.sensor_override: dict[str, float | None] = {}
        self._server = None
        self._ids: dict[str, object] = {}

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.host}:{self.port}/hvac-mpc/"

    # ------------------------------------------------------------------ values served
    def _sensor_value(self, name: str, ua):
        if name in self.sensor_override:
            v = self.sensor_override[name]
        else:
            m = self.measurement()
            v = getattr(m, name)
            if self.calibration is not None and name != "time_s":
                v = self.calibration.sensor_to_raw(name, v)
        if v is None:
            return ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadNoData))
        return ua.DataValue(ua.Variant(float(v), ua.VariantType.Double))

    async def _post_write(self, event, _dispatcher) -> None:
        """A write naming the heartbeat node applies the actuator nodes as one command."""
        ua = _asyncua().ua
        written = [w.NodeId for w in event.request_params.NodesToWrite]
        if self._ids["heartbeat"] not in written:
            return
        aspace = self._server.iserver.aspace
        read = {n: aspace.read_attribute_value(self._ids[n], ua.AttributeIds.Value).Value.Value
                for n in (*INPUTS, "heartbeat")}
        raw = {n: float(read[n]) for n in INPUTS}
        if not all(math.isfinite(v) for v in raw.values()):
            return  # refused: a non-finite output is not applied
        cmd = Command(**raw) if self.calibration is None else self.calibration.command_from_raw(raw)
        hb = int(read["heartbeat"])
        self.received.append((hb, raw, cmd))
        self._on_command(cmd, hb)

    # ------------------------------------------------------------------ server side
    async def _start_server(self) -> None:
        asyncua = _asyncua()
        ua = asyncua.ua
        from asyncua.common.callback import CallbackType

        server = asyncua.Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        server.set_server_name("hvac-mpc simulated box")
        idx = await server.register_namespace(self.namespace)
        box = await server.nodes.objects.add_object(ua.NodeId(node_id(), idx), ua.QualifiedName("HvacBox", idx))

        async def var(path: tuple[str, str], value, vtype, writable: bool = False):
            nid = ua.NodeId(node_id(*path), idx)
            node = await box.add_variable(nid, ua.QualifiedName(path[1], idx), ua.Variant(value, vtype))
            if writable:
                await node.set_writable()
            return nid

        ids: dict[str, object] = {}
        for name in SENSOR_NODES:
            nid = await var(("Sensors", name), 0.0, ua.VariantType.Double)
            server.iserver.set_attribute_value_callback(nid, lambda _n, _a, name=name: self._sensor_value(name, ua))
        folder = "RawSignals" if self.calibration is not None else "Actuators"
        raw = self.calibration.command_raw(self.command) if self.calibration is not None else None
        for name in INPUTS:
            value = raw[name] if raw is not None else float(getattr(self.command, name))
            ids[name] = await var((folder, name), value, ua.VariantType.Double, writable=True)
            other = "Actuators" if folder == "RawSignals" else "RawSignals"
            await var((other, name), math.nan, ua.VariantType.Double)  # present, not taken by this device
        ids["heartbeat"] = await var(("Watchdog", "heartbeat"), 0, ua.VariantType.UInt16, writable=True)
        echo = await var(("Watchdog", "heartbeat_echo"), 0, ua.VariantType.UInt16)
        server.iserver.set_attribute_value_callback(
            echo, lambda _n, _a: ua.DataValue(ua.Variant((self.heartbeat or 0) & 0xFFFF, ua.VariantType.UInt16)))
        status = await var(("Watchdog", "status"), 0, ua.VariantType.UInt16)
        server.iserver.set_attribute_value_callback(
            status, lambda _n, _a: ua.DataValue(ua.Variant(self.status_bits(), ua.VariantType.UInt16)))
        await var(("Watchdog", "signals"), "raw" if self.calibration is not None else "engineering",
                  ua.VariantType.String)
        self._ids = ids
        server.subscribe_server_callback(CallbackType.PostWrite, self._post_write)
        await server.start()
        self._server = server

    async def _stop_server(self) -> None:
        if self._server is not None:
            server, self._server = self._server, None
            await server.stop()

    def start(self, timeout_s: float = 20.0) -> "PlantOpcUaServer":
        _asyncua()
        super().start(timeout_s)
        return self


def main(argv: list[str] | None = None) -> int:
    return run_standalone(argv, PlantOpcUaServer, "OPC UA", 4840)


if __name__ == "__main__":
    raise SystemExit(main())
