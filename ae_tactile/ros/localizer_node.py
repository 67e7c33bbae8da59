"""`localizer` node: PacketArray -> ContactEvent (TOUCH / DETOUCH), markers, diagnostics.

Packets are localized in batches (`ae_tactile.localization.localize`, estimator chosen by
the `method` parameter) by a worker thread that takes every PacketArray queued since its
last pass: one packet costs ~1.5 ms alone but ~0.05 ms in a batch of 64, so the node keeps
the lowest latency when packets are sparse and batches itself up when they come fast. The
geometry comes from the driver's latched `sensor_info` when it arrives (so a bag is
self-describing), else from the parameters. Each accepted packet gives one ContactEvent
on `contacts`: TOUCH for compressive onsets, DETOUCH for rarefactions, stamped at the
emission time (first-sample stamp + onset / fs - travel time from the fitted point to
the nearest element). Rejected packets are counted by reason in `/diagnostics`.
Markers (`markers`, MarkerArray): the fingertip, the PVDF matrix, recent events.
"""
from __future__ import annotations

import math
import sys
import threading
from collections import Counter, deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import Localizer, Reason, available_methods
from ae_tactile.msg import ContactEvent, PacketArray, SensorInfo
from ae_tactile.ros.conversions import ns_to_time_msg, packet_samples, time_msg_to_ns
from ae_tactile.ros.node_utils import LATCHED, run_node
from ae_tactile.ros.markers import EventMarkers, sensor_markers
from ae_tactile.ros.params import Param, declare

LOCALIZER_PARAMS = [
    Param("method", "ml", "Delay estimator: " + ", ".join(available_methods()), choices=tuple(available_methods())),
    Param("min_snr_db", 5.0, "Reject packets below this SNR (dB, docs/conventions.md)", -20.0, 80.0),
    Param("min_confidence", 0.0, "Do not publish events below this confidence", 0.0, 1.0),
    Param("use_sensor_info", True, "Take geometry and gains from the driver's latched sensor_info"),
    Param("radius_m", 10e-3, "Sphere radius R (m), until sensor_info arrives", 1e-3, 0.1),
    Param("element_offset_m", 1.5e-3, "Element offset a (m), until sensor_info arrives", 1e-4, 0.02),
    Param("sound_speed_m_s", 1480.0, "Sound speed c (m/s), until sensor_info arrives", 100.0, 10_000.0),
    Param("reliable_qos", False, "Subscribe to packets reliably (needs a reliable driver; no loss under load)"),
    Param("markers", True, "Publish RViz markers on 'markers'"),
    Param("marker_lifetime_s", 2.0, "How long an event marker stays (fading) (s)", 0.1, 60.0),
    Param("marker_period_s", 0.1, "Marker refresh period (s)", 0.02, 5.0),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics messages (s)", 0.05, 60.0),
]


class LocalizerNode(Node):
    def __init__(self, **kwargs):
        super().__init__("localizer", **kwargs)
        p = self.p = declare(self, LOCALIZER_PARAMS)
        self.geometry = FingertipGeometry(p["radius_m"], p["element_offset_m"], p["sound_speed_m_s"])
        self.channel_gains = None
        self.localizer = Localizer(p["method"], min_snr_db=p["min_snr_db"])
        self.frame_id = ""
        self.pub_events = self.create_publisher(ContactEvent, "contacts", 100)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.pub_markers = self.create_publisher(MarkerArray, "markers", 10) if p["markers"] else None
        self._inbox: deque[PacketArray] = deque()
        self._wake = threading.Event()
        self._running = True
        self._busy = False
        # Best effort by default (matches best-effort and reliable drivers), with a deep
        # history so that a burst waiting for the executor is not overwritten.
        reliability = ReliabilityPolicy.RELIABLE if p["reliable_qos"] else ReliabilityPolicy.BEST_EFFORT
        self.create_subscription(PacketArray, "packets", self._enqueue,
                                 QoSProfile(depth=1000, reliability=reliability))
        if p["use_sensor_info"]:
            self.create_subscription(SensorInfo, "sensor_info", self.on_sensor_info, LATCHED)
        self.counts = Counter()
        self.last_upstream = (0, 0)          # (packets_dropped, frames_bad_crc) seen upstream
        self.events = EventMarkers("", p["marker_lifetime_s"])
        if self.pub_markers is not None:
            self.create_timer(p["marker_period_s"], self.publish_markers)
        self.create_timer(p["diagnostics_period_s"], self.publish_diagnostics)
        self._worker = threading.Thread(target=self._work, name="ae_tactile_localizer", daemon=True)
        self._worker.start()
        self.get_logger().info(f"localizer: method '{p['method']}', min SNR {p['min_snr_db']:g} dB")

    # ------------------------------------------------------------------ batching
    def _enqueue(self, msg: PacketArray) -> None:
        self._inbox.append(msg)
        self._wake.set()

    def idle(self) -> bool:
        """Nothing queued or being localized."""
        return not self._inbox and not self._busy

    def _work(self) -> None:
        while self._running:
            self._wake.wait(0.1)
            self._wake.clear()
            while self._inbox and self._running:
                self._busy = True
                msgs = []
                while self._inbox:
                    msgs.append(self._inbox.popleft())
                try:
                    self.on_packets(msgs)
                except Exception as exc:   # keep localizing; say what went wrong
                    self.get_logger().error(f"localization failed: {exc!r}", throttle_duration_sec=5.0)
                finally:
                    self._busy = False

    def destroy_node(self):
        if not hasattr(self, "_worker"):       # constructor stopped early (bad parameter)
            return super().destroy_node()
        self._running = False
        self._wake.set()
        self._worker.join(1.0)
        return super().destroy_node()

    def on_sensor_info(self, msg: SensorInfo) -> None:
        try:
            self.geometry = FingertipGeometry(msg.radius_m, msg.element_offset_m, msg.sound_speed_m_s)
        except ValueError as exc:
            self.get_logger().error(f"ignoring invalid sensor_info: {exc}")
            return
        gains = np.asarray(msg.channel_gains, dtype=float)
        self.channel_gains = gains if gains.shape == (4,) and np.all(gains > 0) else None
        self.get_logger().info(f"geometry from sensor_info ({msg.serial_number or 'no serial'}): "
                               f"R={msg.radius_m * 1e3:.2f} mm, a={msg.element_offset_m * 1e3:.2f} mm, "
                               f"c={msg.sound_speed_m_s:.0f} m/s")

    # ------------------------------------------------------------------ packets
    def on_packets(self, msgs: list[PacketArray]) -> None:
        """Localize the packets of several PacketArrays, grouped by window length and rate."""
        groups: dict[tuple[int, float], list] = {}
        for msg in msgs:
            self.frame_id = msg.header.frame_id
            self.last_upstream = (msg.packets_dropped, msg.frames_bad_crc)
            for p in msg.packets:
                self.counts["packets"] += 1
                try:
                    x = packet_samples(p)
                except ValueError as exc:
                    self.counts["rejected_MALFORMED"] += 1
                    self.get_logger().warning(str(exc), throttle_duration_sec=5.0)
                    continue
                groups.setdefault((x.shape[1], p.sample_rate_hz), []).append((p, x, msg.header.frame_id))
        for (_, fs), items in groups.items():
            self.localize_group(fs, items)

    def localize_group(self, fs: float, items) -> None:
        windows = np.stack([x for _, x, _ in items])
        onset = np.array([p.onset_index for p, _, _ in items], dtype=np.int64)
        saturated = np.array([p.saturated for p, _, _ in items], dtype=bool)
        res = self.localizer(windows, fs, onset, geometry=self.geometry, saturated=saturated,
                             channel_gains=self.channel_gains)
        travel = self.geometry.arrival_times_s(np.nan_to_num(res.point_m)).min(axis=-1)
        order = np.argsort([time_msg_to_ns(p.stamp) for p, _, _ in items], kind="stable")
        for i in order:
            p, _, frame_id = items[i]
            if not res.accepted[i]:
                self.counts["rejected_" + Reason(int(res.reason[i])).name] += 1
                continue
            if res.confidence[i] < self.p["min_confidence"]:
                self.counts["below_min_confidence"] += 1
                continue
            stamp_ns = time_msg_to_ns(p.stamp) + int(round(p.onset_index * 1e9 / fs - travel[i] * 1e9))
            ev = ContactEvent()
            ev.header.stamp = ns_to_time_msg(stamp_ns)
            ev.header.frame_id = frame_id
            ev.event_type = ContactEvent.DETOUCH if res.polarity[i] < 0 else ContactEvent.TOUCH
            ev.position.x, ev.position.y, ev.position.z = (float(v) for v in res.point_m[i])
            ev.position_covariance = [float(v) for v in res.covariance_m2[i].ravel()]
            ev.polar_angle_rad, ev.azimuth_angle_rad = float(res.polar_rad[i]), float(res.azimuth_rad[i])
            ev.tau_x_s, ev.tau_y_s = float(res.tau_x_s[i]), float(res.tau_y_s[i])
            ev.amplitude_v = float(res.amplitude_v[i])
            ev.confidence = float(res.confidence[i])
            ev.packet_ids = [int(p.sequence_id)]
            ev.emission_rate_hz = ev.spatial_period_m = math.nan
            ev.slip_direction.x = ev.slip_direction.y = ev.slip_direction.z = math.nan
            self.pub_events.publish(ev)
            self.counts["events"] += 1
            self.counts["touch" if ev.event_type == ContactEvent.TOUCH else "detouch"] += 1
            if self.pub_markers is not None:
                self.events.add(ev, self.get_clock().now().nanoseconds)

    # ------------------------------------------------------------------ outputs
    def publish_markers(self) -> None:
        if not self.frame_id:
            return
        now = self.get_clock().now()
        stamp = now.to_msg()
        arr = sensor_markers(self.geometry, self.frame_id, stamp)
        self.events.frame_id = self.frame_id
        arr.markers.extend(self.events.render(now.nanoseconds, stamp).markers)
        self.pub_markers.publish(arr)

    def publish_diagnostics(self) -> None:
        st = DiagnosticStatus()
        st.name = f"{self.get_fully_qualified_name()}: localization"
        rejected = sum(v for k, v in self.counts.items() if k.startswith("rejected_"))
        st.level = DiagnosticStatus.OK
        st.message = f"{self.counts['events']} events, {rejected} packets rejected"
        if self.counts["packets"] and rejected > 0.5 * self.counts["packets"]:
            st.level = DiagnosticStatus.WARN
        st.values = [KeyValue(key=k, value=str(v)) for k, v in sorted(self.counts.items())]
        st.values += [KeyValue(key="method", value=self.p["method"]),
                      KeyValue(key="upstream_packets_dropped", value=str(self.last_upstream[0])),
                      KeyValue(key="upstream_frames_bad_crc", value=str(self.last_upstream[1]))]
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [st]
        self.pub_diag.publish(msg)


def main(args=None) -> int:
    return run_node(LocalizerNode, args)


if __name__ == "__main__":
    sys.exit(main())
