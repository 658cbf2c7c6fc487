"""Roadwatch drivers: everything that touches hardware or a wire (frame sources, Modbus, serial, systemd)."""
