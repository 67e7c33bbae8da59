# SPDX-License-Identifier: Apache-2.0
"""Hex dumps of frames, in the format docs/protocol.md uses for its example frames.

Format: one line per 16 bytes, ``OOOO: hh hh ...`` with a 4-digit hex offset.
``parse_hex`` reads it back (offsets are checked, so a dump cannot silently lose a line).
"""

from __future__ import annotations

import re

_LINE = re.compile(r"^\s*([0-9A-Fa-f]{4,8}):((?:\s+[0-9A-Fa-f]{2})+)\s*$")


def format_hex(data, width: int = 16) -> str:
    """Hex dump of ``data``: lines "0010: ae 7c ..." of ``width`` bytes each."""
    data = bytes(data)
    if isinstance(width, bool) or not isinstance(width, int) or width < 1:
        raise ValueError(f"width must be a positive integer, got {width!r}")
    return "\n".join(
        f"{i:04x}: " + " ".join(f"{b:02x}" for b in data[i : i + width])
        for i in range(0, len(data), width)
    )


def parse_hex(text: str) -> bytes:
    """Bytes of a dump made by ``format_hex`` (blank lines ignored).

    Raises ValueError for a line that is not "offset: bytes" or whose offset does not
    continue the previous lines.
    """
    out = bytearray()
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        m = _LINE.match(line)
        if m is None:
            raise ValueError(f"line {lineno} is not a hex dump line: {line!r}")
        offset = int(m.group(1), 16)
        if offset != len(out):
            raise ValueError(f"line {lineno}: offset 0x{offset:04x}, expected 0x{len(out):04x}")
        out += bytes.fromhex(m.group(2))
    return bytes(out)
