# SPDX-License-Identifier: Apache-2.0
"""A light fingertip for latency benchmarks: pre-rendered PACKET frames written on a pty (or a
TCP connection) at real time, by a process that does nothing else.

    python bench/fingertip_writer.py PACKETS.npz LOG.npz PORT_FILE [pty|tcp]

pty: the driver opens the pty's slave path (as a USB serial device: the kernel's tty layer
hands the bytes over). tcp: the writer listens on 127.0.0.1 and PORT_FILE holds the
``socket://`` URL the driver connects to (no tty layer: the bytes arrive as written).

PACKETS.npz: counts (K, 4, N) int16, due_s (K,) when each packet's window closes (s from
START), first_sample_index (K,), pre_trigger, sample_rate_hz, v_per_count. The writer
opens the port, writes its path (URL) to PORT_FILE, answers the driver's commands (ACK,
STATUS) like the firmware, and after START writes packet k when due_s[k] has passed
(the frame carries the device time of its first sample), STATUS once a second. When the
schedule is done (or on SIGINT/SIGTERM) it saves LOG.npz: written_ns (K,) int64 host
time (time.time_ns, CLOCK_REALTIME, the clock rclpy stamps with) at which packet k's last
byte was written (-1 if not written), and start_ns, the host time of START (so the
schedule's own lag, a backed-up port, shows too). Latency is measured from there:
device bytes -> event. After SIGINT it stops writing, saves the log and keeps the port
open (the driver still reads what the port holds) until SIGTERM; SIGTERM alone ends it.
"""

from __future__ import annotations

import os
import select
import signal
import socket
import sys
import time
import tty

import numpy as np

from ae_tactile.protocol import (
    Ack,
    AckResult,
    Command,
    DeviceState,
    Direction,
    FrameEncoder,
    Packet,
    Status,
    StreamDecoder,
)
from ae_tactile.protocol.frames import Opcode

LINGER_AFTER_STOP_S = 300.0  # [s] the port kept open after SIGINT at most


def main(argv) -> int:
    packets_path, log_path, port_file = argv[1:4]
    d = np.load(packets_path)
    counts, due_s = d["counts"], d["due_s"]
    first_index = d["first_sample_index"]
    pre, fs, vpc = int(d["pre_trigger"]), int(d["sample_rate_hz"]), float(d["v_per_count"])
    n_samples = counts.shape[2]
    k_total = counts.shape[0]
    log = np.full(k_total, -1, dtype=np.int64)
    transport = argv[4] if len(argv) > 4 else "pty"
    if transport == "tcp":
        server = socket.create_server(("127.0.0.1", 0))
        path = f"socket://127.0.0.1:{server.getsockname()[1]}"
    elif transport == "pty":
        master, slave = os.openpty()
        tty.setraw(slave)
        path = os.ttyname(slave)
    else:
        print(f"transport must be pty or tcp, got {transport!r}", file=sys.stderr)
        return 2
    with open(port_file + ".tmp", "w") as fh:
        fh.write(path)
    os.replace(port_file + ".tmp", port_file)
    if transport == "tcp":
        server.settimeout(60.0)
        conn, _ = server.accept()  # the driver connects
        server.close()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # each frame at once
        master = conn.fileno()
    os.set_blocking(master, False)
    enc = FrameEncoder(boot=True)
    dec = StreamDecoder(direction=Direction.HOST_TO_DEVICE)
    t_boot = time.monotonic_ns()
    state = {"acquiring": False, "t0": 0, "t0_wall": 0, "stop": False, "leave": False}

    def now_us() -> int:
        return ((time.monotonic_ns() - t_boot) // 1000) & 0xFFFFFFFF

    out_ready = select.poll()
    out_ready.register(master, select.POLLOUT)

    def write(data: bytes) -> bool:
        """True once every byte is handed over; False if a stop came while the port was
        full (nobody may read any more: a stop does not wait for ever)."""
        view = memoryview(data)
        while view:
            try:
                view = view[os.write(master, view) :]
            except BlockingIOError:  # the port is full: wait until the driver reads
                if state["stop"]:
                    return False
                out_ready.poll(1.0)
        return True

    def status() -> bytes:
        st = DeviceState.TRIGGERED if state["acquiring"] else DeviceState.IDLE
        return enc.encode(
            Status(now_us(), st, fs, vpc, 10, n_samples, pre, 0, 0, (0, 1, 0), "AE-BENCH-0001"),
            now_us(),
        )

    def on_stop(*_):  # SIGINT: stop writing; the port stays open until SIGTERM
        state["stop"] = True

    def on_leave(*_):  # SIGTERM: stop writing and close the port now
        state["stop"] = state["leave"] = True

    signal.signal(signal.SIGINT, on_stop)
    signal.signal(signal.SIGTERM, on_leave)
    # the frame bodies are built (validated) before START: at run time only the header
    # (sequence number, time stamp) and the CRCs are computed
    bodies = [
        Packet(counts[i], fs, vpc, first_sample_index=int(first_index[i]), pre_trigger=pre)
        for i in range(k_total)
    ]
    k = 0
    next_status = time.monotonic() + 1.0
    write(status())
    while not state["stop"]:
        try:
            data = os.read(master, 4096)
        except (BlockingIOError, OSError):
            data = b""
        for f in dec.feed(data):
            cmd = f.body
            if not isinstance(cmd, Command):
                continue
            write(enc.encode(Ack(cmd.command_id, cmd.opcode, AckResult.OK, 0), now_us()))
            if cmd.opcode == Opcode.GET_STATUS:
                write(status())
            elif cmd.opcode == Opcode.START and not state["acquiring"]:
                state["acquiring"] = True
                state["t0"] = time.monotonic_ns()
                state["t0_wall"] = time.time_ns()
            elif cmd.opcode == Opcode.STOP:
                state["acquiring"] = False
        now = time.monotonic()
        if now >= next_status:
            write(status())
            next_status = now + 1.0
        if not state["acquiring"]:
            time.sleep(0.0005)
            continue
        elapsed_s = (time.monotonic_ns() - state["t0"]) * 1e-9
        # a stop also ends a backlog (packets overdue because the port was full)
        while k < k_total and due_s[k] <= elapsed_s and not state["stop"]:
            first_us = int((state["t0"] - t_boot) // 1000 + first_index[k] * 1e6 / fs) & 0xFFFFFFFF
            if not write(enc.encode(bodies[k], first_us)):
                break  # not (wholly) written: its log entry stays -1
            log[k] = time.time_ns()
            k += 1
        if k >= k_total:
            break
        wait = due_s[k] - (time.monotonic_ns() - state["t0"]) * 1e-9
        time.sleep(min(max(wait - 50e-6, 0.0), 0.002))
    np.savez(log_path, written_ns=log, start_ns=np.int64(state["t0_wall"]))
    # keep the pty open so the driver reads everything before the hang-up (closing the
    # master discards what the driver has not read): 1 s after a finished schedule; after
    # a stop (SIGINT) until SIGTERM, as a driver that fell behind may need longer
    t_end = time.monotonic() + (LINGER_AFTER_STOP_S if state["stop"] else 1.0)
    while time.monotonic() < t_end and not state["leave"]:
        try:
            os.read(master, 4096)
        except (BlockingIOError, OSError):
            pass
        time.sleep(0.01)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
