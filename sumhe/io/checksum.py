"""End-to-end protection of CAN frames: CRC-8/SAE-J1850 in byte 0 and a 4-bit rolling counter.

The reference DBC (``dbc/sumhe_ref.dbc``) protects ESP_YAW_RATE and ESP_VEHICLE_SPEED this way: byte 0
is the CRC over bytes 1-7 (poly 0x1D, init 0xFF, xorout 0xFF), the counter is bits 8-11.
"""

from __future__ import annotations


def _table() -> tuple[int, ...]:
    out = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        out.append(crc)
    return tuple(out)


_CRC8_TABLE = _table()


def crc8_j1850(data: bytes) -> int:
    """CRC-8/SAE-J1850 of ``data`` (check value of b"123456789" is 0x4B)."""
    crc = 0xFF
    for b in data:
        crc = _CRC8_TABLE[crc ^ b]
    return crc ^ 0xFF


def protect(payload: bytes) -> bytes:
    """Return ``payload`` with byte 0 set to the CRC of bytes 1..end."""
    return bytes((crc8_j1850(payload[1:]),)) + payload[1:]


def is_intact(payload: bytes) -> bool:
    """True when byte 0 holds the CRC of bytes 1..end."""
    return len(payload) >= 2 and payload[0] == crc8_j1850(payload[1:])


def rolling_counter(payload: bytes) -> int:
    """The 4-bit counter in bits 8-11 (low nibble of byte 1)."""
    return payload[1] & 0x0F
