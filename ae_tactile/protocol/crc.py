# SPDX-License-Identifier: Apache-2.0
"""CRC-32 of the protocol: the IEEE 802.3 / zlib / PNG CRC.

Parameters (Rocksoft notation): width 32, poly 0x04C11DB7 (reflected form
0xEDB88320), init 0xFFFFFFFF, refin = refout = true, xorout 0xFFFFFFFF,
check CRC("123456789") = 0xCBF43926. ``zlib.crc32`` computes exactly this, and
its running form ``crc32(b, crc32(a)) == crc32(a + b)`` is what a firmware gets
from the C reference in docs/protocol.md when it calls ``crc32_update`` in pieces.
"""

from __future__ import annotations

import zlib

#: CRC-32 of the ASCII bytes b"123456789" (the standard check value).
CRC32_CHECK = 0xCBF43926

_POLY_REFLECTED = 0xEDB88320


def crc32(data, crc: int = 0) -> int:
    """CRC-32 (IEEE) of ``data`` (any bytes-like object), continuing from ``crc``."""
    return zlib.crc32(data, crc)


def crc32_reference(data, crc: int = 0) -> int:
    """Bit-by-bit CRC-32, a line-by-line transcription of the C snippet in docs/protocol.md.

    Slow (pure Python); exists so the tests can prove that the documented algorithm
    and ``zlib.crc32`` agree.
    """
    crc = (~crc) & 0xFFFFFFFF
    for byte in bytes(data):
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (_POLY_REFLECTED if crc & 1 else 0)
    return (~crc) & 0xFFFFFFFF
