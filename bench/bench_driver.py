# SPDX-License-Identifier: Apache-2.0
"""Driver node throughput and CPU in raw-packet mode (pipeline:=false, the set-up for
recording): PACKET frames pushed through a pty at fixed rates, published as PacketArray.
(The in-process pipeline's latency and sustained rate: bench/bench_system.py.)

A writer thread plays the device: it ACKs the driver's commands and writes PACKET
frames (4 x 400 int16, the default window) at a target rate with proper sequence
numbers and device timestamps. The `driver` executable runs as its own process
(reliable QoS); this process subscribes to `packets` and counts what arrives.
For each rate: packets sent / published / received, drops counted by the driver,
bytes/s, and the driver process's CPU (user + system time from /proc) per second.

Run: make bench-driver   (results: bench/results/driver.json)
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import threading
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

RATES = [int(r) for r in os.environ.get("AE_BENCH_RATES", "500,1000,2000,5000,10000").split(",")]
SECONDS = 4.0
N = 400


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class FakeDevice(threading.Thread):
    """Writes PACKET frames at `rate` per second on the pty master; ACKs commands."""

    def __init__(self, master: int):
        super().__init__(daemon=True)
        self.master = master
        self.encoder = FrameEncoder(boot=True)
        self.decoder = StreamDecoder(direction=Direction.HOST_TO_DEVICE)
        rng = np.random.default_rng(0)
        self.samples = rng.integers(-300, 300, (4, N)).astype(np.int16)
        self.rate = 0.0
        self.sent = 0
        self.bytes = 0
        self.index = 0
        self.t0 = time.monotonic_ns()
        self.stop = False
        os.set_blocking(master, False)

    def now_us(self) -> int:
        return ((time.monotonic_ns() - self.t0) // 1000) & 0xFFFFFFFF

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master, view)
                view = view[n:]
            except BlockingIOError:
                time.sleep(0.0002)

    def run(self) -> None:
        next_status = 0.0
        due = time.monotonic()
        while not self.stop:
            try:
                data = os.read(self.master, 4096)
            except (BlockingIOError, OSError):
                data = b""
            for f in self.decoder.feed(data):
                if isinstance(f.body, Command):
                    self.write(
                        self.encoder.encode(
                            Ack(f.body.command_id, f.body.opcode, AckResult.OK, 0), self.now_us()
                        )
                    )
            now = time.monotonic()
            if now >= next_status:
                self.write(
                    self.encoder.encode(
                        Status(
                            self.now_us(),
                            DeviceState.TRIGGERED,
                            10_000_000,
                            2**-11,
                            10,
                            N,
                            80,
                            0,
                            0,
                            (0, 1, 0),
                            "BENCH",
                        ),
                        self.now_us(),
                    )
                )
                next_status = now + 1.0
            rate = self.rate
            if rate <= 0:
                time.sleep(0.001)
                due = time.monotonic()
                continue
            while due <= now:
                body = Packet(
                    self.samples, 10_000_000, 2**-11, first_sample_index=self.index, pre_trigger=80
                )
                frame = self.encoder.encode(body, self.now_us())
                self.write(frame)
                self.index += 1000
                self.sent += 1
                self.bytes += len(frame)
                due += 1.0 / rate
            time.sleep(0.0005)


def main() -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from ae_tactile.msg import PacketArray

    root = os.environ.get(
        "AE_TACTILE_ROOT", os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    )
    exe = os.path.join(root, "install", "ae_tactile", "lib", "ae_tactile", "driver")
    os.environ.setdefault("ROS_DOMAIN_ID", "77")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    master, slave = os.openpty()
    tty.setraw(slave)
    port = os.ttyname(slave)
    dev = FakeDevice(master)
    dev.start()
    driver = subprocess.Popen(
        [
            exe,
            "--ros-args",
            "-p",
            f"port:={port}",
            "-p",
            "reliable_qos:=true",
            "-p",
            "pipeline:=false",
            "-p",
            "queue_max_batches:=100000",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    rclpy.init()
    node = rclpy.create_node("bench_listener")
    received = {"packets": 0, "dropped": 0}

    def on_msg(msg):
        received["packets"] += len(msg.packets)
        received["dropped"] = msg.packets_dropped

    node.create_subscription(
        PacketArray,
        "packets",
        on_msg,
        QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE),
    )
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    t_end = time.monotonic() + 5.0
    while time.monotonic() < t_end:  # discovery + driver start-up
        ex.spin_once(timeout_sec=0.05)
    rows = []
    for rate in RATES:
        sent0, bytes0, recv0 = dev.sent, dev.bytes, received["packets"]
        cpu0, t0 = cpu_seconds(driver.pid), time.monotonic()
        dev.rate = rate
        while time.monotonic() - t0 < SECONDS:
            ex.spin_once(timeout_sec=0.01)
        dev.rate = 0
        t1 = time.monotonic()
        cpu1 = cpu_seconds(driver.pid)
        drain = time.monotonic() + 3.0
        while time.monotonic() < drain and received["packets"] - recv0 < dev.sent - sent0:
            ex.spin_once(timeout_sec=0.01)
        sent, got = dev.sent - sent0, received["packets"] - recv0
        row = {
            "target_packets_per_s": rate,
            "sent": sent,
            "received": got,
            "lost": sent - got,
            "driver_reported_dropped_total": received["dropped"],
            "sent_packets_per_s": sent / (t1 - t0),
            "bytes_per_s": (dev.bytes - bytes0) / (t1 - t0),
            "driver_cpu_percent_of_one_core": 100.0 * (cpu1 - cpu0) / (t1 - t0),
        }
        rows.append(row)
        print(
            f"{rate:>6} pkt/s target: sent {sent} received {got} lost {sent - got} "
            f"| {row['bytes_per_s'] / 1e6:6.1f} MB/s "
            f"| driver CPU {row['driver_cpu_percent_of_one_core']:5.1f} %",
            flush=True,
        )
    dev.stop = True
    driver.send_signal(2)
    driver.wait(10)
    ex.shutdown()
    node.destroy_node()
    rclpy.shutdown()
    out = {
        "benchmark": "driver node over a pty, PACKET frames 4x400 int16, reliable QoS",
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "seconds_per_rate": SECONDS,
        "rows": rows,
    }
    os.makedirs(os.path.join(root, "bench", "results"), exist_ok=True)
    with open(os.path.join(root, "bench", "results", "driver.json"), "w") as fh:
        json.dump(out, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
