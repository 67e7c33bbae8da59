"""`slip_detector` node: localized TOUCH / DETOUCH events -> slip precursors, slip, texture.

Feeds the localizer's ContactEvents (`contacts`) to the core `ae_tactile.slip.SlipDetector`
and publishes what it finds on `slip` (ContactEvent SLIP_PRECURSOR / SLIP / TEXTURE), the
finger's latched `contact_state` (ContactState, transient local: a hand controller can
read it at any time), and markers. The sliding speed for TEXTURE spatial periods comes
from the `sliding_speed_m_s` parameter or the `sliding_speed` topic (std_msgs/Float64, m/s).
Every field of `SlipConfig` is a parameter of the same name (docs/slip.md).
"""
from __future__ import annotations

import dataclasses
import math
import sys
from collections import deque

import numpy as np
from rclpy.node import Node
from std_msgs.msg import Float64
from visualization_msgs.msg import MarkerArray

from ae_tactile.msg import ContactEvent, ContactState
from ae_tactile.ros.conversions import ns_to_time_msg, time_msg_to_ns
from ae_tactile.ros.node_utils import LATCHED, run_node
from ae_tactile.ros.markers import EventMarkers
from ae_tactile.ros.params import Param, ParameterError, declare
from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector

NODE_PARAMS = [
    Param("advance_lag_s", 0.02, "Least time the detector's clock trails ROS time, so events still in "
          "flight are not overtaken (s); it grows to 1.5 x the latency seen over the last 2 s", 0.0, 1.0),
    Param("advance_period_s", 0.02, "Period of the time-keeping tick (s)", 0.001, 1.0),
    Param("marker_period_s", 0.1, "Marker refresh period (s)", 0.02, 5.0),
    Param("frame_id", "", "Frame of the outputs; empty = the incoming events' frame"),
    Param("markers", True, "Publish slip markers on 'markers'"),
]


def slip_config_params() -> list[Param]:
    """One parameter per SlipConfig field (numbers and bools; None-able speed as 0.0)."""
    out = []
    for f in dataclasses.fields(SlipConfig):
        default = f.default
        if default is None or f.name == "sliding_speed_m_s":
            default = 0.0
        if not isinstance(default, (bool, int, float)):
            continue
        out.append(Param(f.name, default, f"SlipConfig.{f.name} (docs/slip.md)"
                         + ("; 0 = unknown" if f.name == "sliding_speed_m_s" else "")))
    return out


class SlipDetectorNode(Node):
    def __init__(self, **kwargs):
        super().__init__("slip_detector", **kwargs)
        self.p = declare(self, NODE_PARAMS)
        cfg_values = declare(self, slip_config_params())
        if cfg_values.get("sliding_speed_m_s", 0.0) <= 0.0:
            cfg_values["sliding_speed_m_s"] = None
        try:
            self.detector = SlipDetector(SlipConfig(**cfg_values))
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"slip detector parameters: {exc}") from exc
        self.pub_slip = self.create_publisher(ContactEvent, "slip", 100)
        self.pub_state = self.create_publisher(ContactState, "contact_state", LATCHED)
        self.pub_markers = self.create_publisher(MarkerArray, "markers", 10) if self.p["markers"] else None
        self.markers = EventMarkers("", 2.0, namespace="ae_tactile/slip")
        self.create_subscription(ContactEvent, "contacts", self.on_contact, 1000)
        self.create_subscription(Float64, "sliding_speed", self.on_speed, 10)
        self.create_timer(self.p["advance_period_s"], self.tick)
        if self.pub_markers is not None:
            self.create_timer(self.p["marker_period_s"], self.publish_markers)
        self.frame_id = self.p["frame_id"]
        self.last_state_key = None
        self.last_state_pub_ns = 0
        self.published = 0
        self.received = 0
        self._latencies: deque[tuple[int, int]] = deque()     # (receive ns, latency ns), last 2 s
        self.publish_state(force=True)

    def on_speed(self, msg: Float64) -> None:
        v = float(msg.data)
        try:
            self.detector.set_sliding_speed(v if v > 0 and math.isfinite(v) else None)
        except ValueError as exc:
            self.get_logger().warning(f"sliding_speed {v} ignored: {exc}", throttle_duration_sec=5.0)

    def on_contact(self, msg: ContactEvent) -> None:
        self.received += 1
        if msg.event_type not in (ContactEvent.TOUCH, ContactEvent.DETOUCH):
            return
        if not self.frame_id:
            self.frame_id = msg.header.frame_id
        now = self.get_clock().now().nanoseconds
        self._latencies.append((now, now - time_msg_to_ns(msg.header.stamp)))
        while self._latencies and now - self._latencies[0][0] > 2_000_000_000:
            self._latencies.popleft()
        try:
            ev = LocalizedEvent(
                time_ns=time_msg_to_ns(msg.header.stamp),
                point_m=np.array([msg.position.x, msg.position.y, msg.position.z]),
                covariance_m2=np.asarray(msg.position_covariance, dtype=float).reshape(3, 3),
                polarity=1 if msg.event_type == ContactEvent.TOUCH else -1,
                amplitude_v=float(msg.amplitude_v), confidence=float(min(max(msg.confidence, 0.0), 1.0)),
                packet_id=int(msg.packet_ids[0]) if len(msg.packet_ids) else -1)
        except (TypeError, ValueError) as exc:
            self.get_logger().warning(f"contact event rejected: {exc}", throttle_duration_sec=5.0)
            return
        rejected = self.detector.counts.get("rejected_out_of_order", 0)
        for out in self.detector.process(ev):
            self.publish_event(out)
        if self.detector.counts.get("rejected_out_of_order", 0) > rejected:
            self.get_logger().warning("contact event older than the detector's clock dropped "
                                      "(raise advance_lag_s)", throttle_duration_sec=5.0)
        self.publish_state()

    def lag_ns(self) -> int:
        """How far the detector's clock trails ROS time: advance_lag_s, or 1.5 x the largest
        delivery latency of the last 2 s when that is more (a loaded host), so that events
        in flight are never older than the detector's clock when they arrive."""
        seen = max((lat for _, lat in self._latencies), default=0)
        return max(int(self.p["advance_lag_s"] * 1e9), int(1.5 * seen))

    def tick(self) -> None:
        now = self.get_clock().now().nanoseconds
        self.detector.advance(now - self.lag_ns())
        self.publish_state()

    def publish_markers(self) -> None:
        if self.frame_id and self.markers.events:
            now = self.get_clock().now()
            self.markers.frame_id = self.frame_id
            self.pub_markers.publish(self.markers.render(now.nanoseconds, now.to_msg()))

    def publish_event(self, out) -> None:
        ev = ContactEvent()
        ev.header.stamp = ns_to_time_msg(out.time_ns)
        ev.header.frame_id = self.frame_id
        ev.event_type = int(out.kind)
        ev.position.x, ev.position.y, ev.position.z = (float(v) for v in out.position_m)
        ev.position_covariance = [float(v) for v in np.asarray(out.covariance_m2, dtype=float).ravel()]
        x, y, z = (float(v) for v in out.position_m)
        ev.polar_angle_rad, ev.azimuth_angle_rad = math.atan2(math.hypot(x, y), z), math.atan2(y, x)
        ev.tau_x_s = ev.tau_y_s = math.nan
        ev.amplitude_v = math.nan
        ev.confidence = float(out.confidence)
        ev.packet_ids = [int(i) for i in out.packet_ids]
        ev.emission_rate_hz = float(out.emission_rate_hz)
        ev.spatial_period_m = float(out.spatial_period_m)
        d = np.asarray(out.slip_direction, dtype=float)
        ev.slip_direction.x, ev.slip_direction.y, ev.slip_direction.z = (float(v) for v in d)
        self.pub_slip.publish(ev)
        self.published += 1
        if self.pub_markers is not None:
            self.markers.add(ev, self.get_clock().now().nanoseconds)

    def publish_state(self, force: bool = False) -> None:
        st = self.detector.state
        key = (int(st.state), int(st.since_ns), int(st.contact_id))
        now = self.get_clock().now().nanoseconds
        if not force and key == self.last_state_key and now - self.last_state_pub_ns < 1_000_000_000:
            return
        self.last_state_key, self.last_state_pub_ns = key, now
        msg = ContactState()
        msg.header.stamp = ns_to_time_msg(st.time_ns if st.time_ns > 0 else now)
        msg.header.frame_id = self.frame_id
        msg.state = int(st.state)
        msg.state_since = ns_to_time_msg(max(int(st.since_ns), 0))
        p = np.asarray(st.contact_point_m, dtype=float)
        msg.contact_point.x, msg.contact_point.y, msg.contact_point.z = (float(v) for v in p)
        msg.slip_emission_rate_hz = float(st.slip_emission_rate_hz)
        msg.precursor_count = int(st.precursor_count)
        self.pub_state.publish(msg)


def main(args=None) -> int:
    return run_node(SlipDetectorNode, args)


if __name__ == "__main__":
    sys.exit(main())
