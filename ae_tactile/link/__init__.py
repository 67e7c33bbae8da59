# SPDX-License-Identifier: Apache-2.0
"""Host side of the fingertip serial link (pure Python, no rclpy).

`FingertipLink` owns the port (any pyserial URL: a device path, a pty, ``socket://``,
``loop://``), reads it in a background thread, decodes frames with the protocol's
incremental decoder, maps device time to host time (`DeviceClockMapper`), turns
PACKET frames (triggered mode) or STREAM blocks cut by the packet detector (stream
mode) into `PacketRecord`s, and hands them out in bounded per-read-cycle batches.

Liveness is valid frames, not bytes. States: ``disconnected`` (port closed),
``connecting`` (port open, no valid frame yet), ``connected`` (a valid frame within
``link_timeout_s``). A real read error (EIO, a hang-up), or ``link_timeout_s`` without a
valid frame (a dead device, a reset device that stays silent, a wrong baud rate that
only yields garbage) closes the port; it is reopened with exponential back-off, the
device re-configured, acquisition restarted and the clock mapping re-synced. A
spurious wake-up (readable but nothing to read, EAGAIN) is counted, never a disconnect.
A partial frame left waiting ``stall_report_s`` with no byte arriving is reported
(``stalled_frames``, a warning) and kept: the device may still finish it, and a new
frame cuts it short at once (the decoder's rule 3), so no valid frame is lost to a pause.

Nothing is silently lost: every byte (decoded or discarded), every rejected frame by
reason, duplicates, sequence gaps, queue overflows, stream gaps and packets refused by
the link (non-finite volts) are counted (`stats()`). No input stops the reader thread:
an unexpected error while handling a frame is counted (``internal_errors``) and logged.

Memory is bounded: the decoder holds < MAX_FRAME_LEN + ``read_chunk_bytes`` bytes, the
hand-over queue ``queue_max_batches`` batches of one read each (a read of
``read_chunk_bytes`` yields at most read_chunk_bytes / 60 packets; 2 float32 bytes per
wire byte of samples), the ACK table 64 entries; overload is dropped and counted.

Reads are neither byte-by-byte nor timeout-bound: each cycle blocks for the first
byte (up to ``read_timeout_s``, only when idle) and then takes everything waiting.

Modules, along the data flow: `port` (the input: open, read, drain), `reader`
(`FingertipLink`: the thread, reconnects, decoding, hand-over, counters), `commands`
(configure, clock-sync round trips, ACKs), `packets` (frames -> `PacketRecord`s),
`frontend` (the per-packet volts / noise / onset kernel), `config` (`LinkConfig`).
"""

from .config import MODES, LinkConfig
from .frontend import packet_volts_noise_onset, warm_up, window_noise_and_onset
from .packets import PacketBatch, PacketBuilder, PacketRecord
from .port import PORT_ERRORS, TTY_LINE_BUFFER_BYTES, PortBusy, PortLock, SerialPort
from .reader import COUNTER_NAMES, LOG, FingertipLink

__all__ = [
    "COUNTER_NAMES",
    "LOG",
    "MODES",
    "PORT_ERRORS",
    "TTY_LINE_BUFFER_BYTES",
    "FingertipLink",
    "LinkConfig",
    "PacketBatch",
    "PacketBuilder",
    "PacketRecord",
    "PortBusy",
    "PortLock",
    "SerialPort",
    "packet_volts_noise_onset",
    "warm_up",
    "window_noise_and_onset",
]
