"""Builds the enabled controller outputs (Modbus TCP/RTU, serial line) for a site."""

from __future__ import annotations

import importlib

from appliance.config import SiteConfig
from appliance.types import Output

_OUTPUTS = (
    ("modbus_tcp", "drivers.modbus_server", "ModbusTcpOutput"),
    ("modbus_rtu", "drivers.modbus_server", "ModbusRtuOutput"),
    ("serial", "drivers.serial_line", "SerialLineOutput"),
)


def build_outputs(site: SiteConfig) -> list[Output]:
    """One output per enabled section of ``[outputs]``; the driver modules load only when used."""
    outs: list[Output] = []
    for section, module, cls in _OUTPUTS:
        if not getattr(site.outputs, section).enabled:
            continue
        try:
            factory = getattr(importlib.import_module(module), cls)
        except (ImportError, AttributeError) as e:
            raise RuntimeError(f"outputs.{section}: output driver {module}.{cls} is not available ({e})") from None
        outs.append(factory(site))
    return outs
