"""Sensor I/O: pure parsers (NMEA, CAN frames) and thin async adapters (serial, CAN bus, UDP)."""
