"""Message demo: two rclpy nodes exchange the package's three message types over DDS.

`demo_source` publishes, once per period, a PacketArray holding one synthetic Packet
(a 300 kHz tone burst shifted across the 4 channels by the exact delays of a touch
at a known point), the same Packet alone, and a ContactEvent for that point;
`demo_printer` subscribes and prints what it receives. This shows the messages and
the transport; the full pipeline (simulated fingertip -> driver -> localizer ->
slip detector) replaces it as the later parts land.
"""
from __future__ import annotations

import math
import sys

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.msg import ContactEvent, Packet, PacketArray
from ae_tactile.ros.conversions import make_packet, packet_samples, time_msg_to_ns

FRAME_ID = "ae_tactile_fingertip"


def tone_burst_packet(geometry: FingertipGeometry, point_m, sample_rate_hz=10e6,
                      n_samples=400, onset_index=100, f0_hz=300e3):
    """(4, N) Gaussian tone burst; channel k starts at its exact arrival time (volts)."""
    t = np.arange(n_samples) / sample_rate_hz
    arrival = geometry.arrival_times_s(point_m)
    t0 = onset_index / sample_rate_hz + (arrival - arrival.min())[:, None]
    u = t[None, :] - t0
    env = np.exp(-0.5 * ((u - 5e-6) / 2e-6) ** 2) * (u >= 0)
    return 0.1 * env * np.sin(2 * math.pi * f0_hz * u)


class DemoSource(Node):
    def __init__(self, period_s: float = 0.5):
        super().__init__("demo_source")
        self.geometry = FingertipGeometry()
        self.pub_array = self.create_publisher(PacketArray, "packets", 10)
        self.pub_packet = self.create_publisher(Packet, "demo/packet", 10)
        self.pub_event = self.create_publisher(ContactEvent, "contacts", 10)
        self.sequence_id = 0
        self.timer = self.create_timer(period_s, self.tick)

    def tick(self):
        angle = 0.7 * self.sequence_id
        point = self.geometry.surface_point_from_xy(2.5e-3 * math.cos(angle), 2.5e-3 * math.sin(angle))
        now = self.get_clock().now()
        stamp_ns = now.nanoseconds
        packet = make_packet(tone_burst_packet(self.geometry, point), stamp_ns=stamp_ns,
                             sample_rate_hz=10e6, onset_index=100, sequence_id=self.sequence_id,
                             noise_rms_v=0.0)
        arr = PacketArray()
        arr.header.stamp = now.to_msg()
        arr.header.frame_id = FRAME_ID
        arr.packets = [packet]
        self.pub_array.publish(arr)
        self.pub_packet.publish(packet)
        ev = ContactEvent()
        ev.header = arr.header
        ev.event_type = ContactEvent.TOUCH
        ev.position.x, ev.position.y, ev.position.z = (float(v) for v in point)
        ev.position_covariance = list(np.diag([1e-10, 1e-10, 1e-10]).ravel())
        polar, azimuth = self.geometry.angles_from_points(point)
        ev.polar_angle_rad, ev.azimuth_angle_rad = float(polar), float(azimuth)
        ev.tau_x_s, ev.tau_y_s = (float(v) for v in self.geometry.exact_delays_s(point))
        ev.amplitude_v = 0.1
        ev.confidence = 1.0
        ev.packet_ids = [self.sequence_id]
        ev.emission_rate_hz = math.nan
        ev.spatial_period_m = math.nan
        ev.slip_direction.x = ev.slip_direction.y = ev.slip_direction.z = math.nan
        self.pub_event.publish(ev)
        self.sequence_id += 1


class DemoPrinter(Node):
    def __init__(self):
        super().__init__("demo_printer")
        self.received = {"PacketArray": 0, "Packet": 0, "ContactEvent": 0}
        self.create_subscription(PacketArray, "packets", self.on_array, 10)
        self.create_subscription(Packet, "demo/packet", self.on_packet, 10)
        self.create_subscription(ContactEvent, "contacts", self.on_event, 10)

    def on_array(self, msg: PacketArray):
        self.received["PacketArray"] += 1
        p = msg.packets[0]
        x = packet_samples(p)
        print(f"PacketArray  frame={msg.header.frame_id} packets={len(msg.packets)} "
              f"dropped={msg.packets_dropped} bad_crc={msg.frames_bad_crc} | first: seq={p.sequence_id} "
              f"{x.shape[0]}x{x.shape[1]} @ {p.sample_rate_hz / 1e6:.0f} MS/s, "
              f"peak {np.abs(x).max() * 1e3:.1f} mV")

    def on_packet(self, msg: Packet):
        self.received["Packet"] += 1
        print(f"Packet       seq={msg.sequence_id} stamp={time_msg_to_ns(msg.stamp)} ns "
              f"onset={msg.onset_index} saturated={msg.saturated}")

    def on_event(self, msg: ContactEvent):
        self.received["ContactEvent"] += 1
        p = msg.position
        print(f"ContactEvent TOUCH at ({p.x * 1e3:+.2f}, {p.y * 1e3:+.2f}, {p.z * 1e3:+.2f}) mm "
              f"tau=({msg.tau_x_s * 1e9:+.1f}, {msg.tau_y_s * 1e9:+.1f}) ns packets={list(msg.packet_ids)}")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    cycles = int(argv[0]) if argv else 6
    print("ae_tactile message demo: node 'demo_source' publishes PacketArray, Packet and "
          "ContactEvent over DDS; node 'demo_printer' receives and prints them. "
          "(The simulated-fingertip pipeline replaces this demo as it lands.)", flush=True)
    rclpy.init()
    source, printer = DemoSource(period_s=0.25), DemoPrinter()
    executor = SingleThreadedExecutor()
    executor.add_node(source)
    executor.add_node(printer)
    try:
        while source.sequence_id < cycles:
            executor.spin_once(timeout_sec=0.1)
        for _ in range(10):
            executor.spin_once(timeout_sec=0.05)
    finally:
        print(f"received: {printer.received}", flush=True)
        executor.shutdown()
        source.destroy_node()
        printer.destroy_node()
        rclpy.try_shutdown()
    return 0 if all(v > 0 for v in printer.received.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
