# SPDX-License-Identifier: Apache-2.0
"""`localizer` node: PacketArray -> localized emissions (Emission), markers, diagnostics.

The replay half of the velodyne-style split: the driver localizes in-process by default;
this node does the same work (`ae_tactile.pipeline.PacketLocalizer`, the same code) on a
`packets` topic, e.g. from a bag or a driver run with ``pipeline:=false``. A worker thread
takes every PacketArray queued since its last pass (one packet alone takes the
single-packet path, a backlog is localized in batches). The
geometry comes from the driver's latched `sensor_info` when it arrives (so a bag is
self-describing), else from the parameters. Each accepted emission (one per packet, or
several from a window holding overlapping emissions) goes out as an Emission on
`localized` with its polarity (+1 compression, -1 rarefaction) and the reading UNKNOWN
(the `slip_detector` node reads it and publishes `contacts`, `slip`, `emissions` and
`contact_state`), stamped at the emission time (first-sample stamp + onset / fs - travel
time from the fitted point to the nearest element). Rejected packets are counted by reason
in `/diagnostics`.
Markers (`markers`, MarkerArray): the fingertip, the PVDF matrix, recent events.
"""

from __future__ import annotations

import sys
import threading
from collections import deque

from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from visualization_msgs.msg import MarkerArray

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.msg import Emission, PacketArray, SensorInfo
from ae_tactile.pipeline import ContactPipeline, PacketView
from ae_tactile.records import emission_record
from ae_tactile.ros.conversions import emission_msg, packet_samples, time_msg_to_ns
from ae_tactile.ros.diagnostics import pipeline_statuses
from ae_tactile.ros.driver_params import EMISSION_QOS
from ae_tactile.ros.markers import EventMarkers, sensor_markers
from ae_tactile.ros.node_utils import LATCHED, run_node
from ae_tactile.ros.params import (
    LOCALIZATION_PARAMS,
    Param,
    ParamSet,
    changes_for_localizer,
    declare,
    make_packet_localizer,
    tunable,
)

LOCALIZER_PARAMS = [
    Param(
        "use_sensor_info", True, "Take geometry and gains from the driver's latched sensor_info"
    ),
    Param("radius_m", 10e-3, "Sphere radius R, until sensor_info arrives", 1e-3, 0.1),
    Param("element_offset_m", 1.5e-3, "Element offset a, until sensor_info arrives", 1e-4, 0.02),
    Param("sound_speed_m_s", 1480.0, "Sound speed c, until sensor_info arrives", 100.0, 10_000.0),
    Param(
        "reliable_qos",
        False,
        "Subscribe to packets reliably (needs a reliable driver; no loss under load)",
    ),
    tunable(Param("markers", True, "Publish RViz markers on 'markers'")),
    Param("marker_lifetime_s", 2.0, "How long an event marker stays (fading)", 0.1, 60.0),
    Param("marker_period_s", 0.1, "Marker refresh period", 0.02, 5.0),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics messages", 0.05, 60.0),
    Param(
        "wait_for_subscribers",
        0,
        "Subscribe to 'packets' only once this many subscribers are matched on 'localized' "
        "(the slip_detector), so that with the driver's wait_for_subscribers the driver "
        "starts only when the whole chain listens and no first event is lost (0: at once)",
        0,
        100,
    ),
]


class LocalizerNode(Node):
    def __init__(self, **kwargs):
        super().__init__("localizer", **kwargs)
        p = self.p = declare(self, LOCALIZER_PARAMS)
        self.loc_params = ParamSet(
            self, LOCALIZATION_PARAMS, "localization.", on_change=self._on_localization_change
        )
        lp = self.loc_params.values
        self.geometry = FingertipGeometry(
            p["radius_m"], p["element_offset_m"], p["sound_speed_m_s"]
        )
        self.localizer = make_packet_localizer(lp, geometry=self.geometry)
        self.counts = self.localizer.counts
        # the driver's pipeline without its slip stage: the same localization, overlap
        # hand-off and duplicate check as the live path
        self.pipeline = ContactPipeline(self.localizer, None)
        self.pipeline.overlap_inline_max = int(lp["overlap_inline_max"])
        self.frame_id = ""
        self.pub_events = self.create_publisher(Emission, "localized", EMISSION_QOS)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.pub_markers = self.create_publisher(MarkerArray, "markers", 10)
        self._inbox: deque[PacketArray] = deque()
        self._wake = threading.Event()
        self._running = True
        self._busy = True  # until the worker has warmed up the localizer (see _work)
        # Best effort by default (matches best-effort and reliable drivers), with a deep
        # history so that a burst waiting for the executor is not overwritten.
        reliability = (
            ReliabilityPolicy.RELIABLE if p["reliable_qos"] else ReliabilityPolicy.BEST_EFFORT
        )
        self._packets_qos = QoSProfile(depth=1000, reliability=reliability)
        if p["wait_for_subscribers"] > 0:
            self._subscribe_timer = self.create_timer(0.01, self._subscribe_when_matched)
        else:
            self._subscribe_packets()
        if p["use_sensor_info"]:
            self.create_subscription(SensorInfo, "sensor_info", self.on_sensor_info, LATCHED)
        self.last_upstream = (0, 0)  # (packets_dropped, frames_bad_crc) seen upstream
        self.events = EventMarkers("", p["marker_lifetime_s"])
        self.create_timer(p["marker_period_s"], self.publish_markers)
        self.create_timer(p["diagnostics_period_s"], self.publish_diagnostics)
        self._worker = threading.Thread(
            target=self._work, name="ae_tactile_localizer", daemon=True
        )
        self._worker.start()
        self.get_logger().info(
            f"localizer: method '{lp['method']}', min SNR {lp['min_snr_db']:g} dB"
        )

    def _subscribe_packets(self) -> None:
        self.create_subscription(PacketArray, "packets", self._enqueue, self._packets_qos)

    def _subscribe_when_matched(self) -> None:
        """A managed start: the driver counts this node among its `packets` subscribers only
        once the slip_detector listens on `localized` (an emission published before it is
        matched would be lost: `localized` keeps no history for late joiners)."""
        if self.pub_events.get_subscription_count() >= self.p["wait_for_subscribers"]:
            self._subscribe_timer.cancel()
            self._subscribe_packets()
            self.get_logger().info("'localized' has its subscribers: listening on 'packets'")

    def _on_localization_change(self, changes: dict) -> None:
        self.localizer.update(**changes_for_localizer(changes))
        if "reject_interference" in changes:
            self.localizer.set_interference(changes["reject_interference"])
        if "overlap_inline_max" in changes:
            self.pipeline.overlap_inline_max = int(changes["overlap_inline_max"])

    # ------------------------------------------------------------------ batching
    def _enqueue(self, msg: PacketArray) -> None:
        self._inbox.append(msg)
        self._wake.set()

    def idle(self) -> bool:
        """Nothing queued or being localized (overlapping windows included)."""
        return (
            not self._inbox
            and not self._busy
            and self.pipeline.idle()
        )

    def _work(self) -> None:
        # Compile / load the kernels before the first packet (1-2 s from numba's cache;
        # packets arriving meanwhile wait in the inbox, none is lost).
        try:
            self.localizer.warm_up()
        except Exception as exc:  # the first packets then pay for it; say why
            self.get_logger().warning(f"localizer warm-up failed: {exc!r}")
        self._busy = False
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
                except Exception as exc:  # keep localizing; say what went wrong
                    self.get_logger().error(
                        f"localization failed: {exc!r}", throttle_duration_sec=5.0
                    )
                finally:
                    self._busy = False

    def destroy_node(self):
        if not hasattr(self, "_worker"):  # constructor stopped early (bad parameter)
            return super().destroy_node()
        self._running = False
        self._wake.set()
        if self._worker.ident is not None:  # not started when stopped while being built
            self._worker.join(1.0)
        self.pipeline.close()
        return super().destroy_node()

    def on_sensor_info(self, msg: SensorInfo) -> None:
        try:
            geometry = FingertipGeometry(msg.radius_m, msg.element_offset_m, msg.sound_speed_m_s)
            self.localizer.update(geometry=geometry, channel_gains=list(msg.channel_gains))
        except ValueError as exc:
            self.get_logger().error(f"ignoring invalid sensor_info: {exc}")
            return
        self.geometry = geometry
        self.hardware_id = msg.serial_number or self.hardware_id
        self.get_logger().info(
            f"geometry from sensor_info ({msg.serial_number or 'no serial'}): "
            f"R={msg.radius_m * 1e3:.2f} mm, a={msg.element_offset_m * 1e3:.2f} mm, "
            f"c={msg.sound_speed_m_s:.0f} m/s"
        )

    # ------------------------------------------------------------------ packets
    hardware_id = "unknown fingertip"
    _last_sequence_id = None

    def _account_sequence(self, sid: int) -> None:
        """Packets that never arrived (a sequence gap: a message lost on the way, e.g. too
        large for best-effort delivery) are counted as ``packets_missing``; a restart of the
        driver (ids going back) restarts the count."""
        last = self._last_sequence_id
        if last is not None and sid > last + 1:
            self.counts["packets_missing"] += sid - last - 1
            self.get_logger().warning(
                f"{sid - last - 1} packets never arrived (sequence ids {last + 1}..{sid - 1})",
                throttle_duration_sec=5.0,
            )
        self._last_sequence_id = sid

    def on_packets(self, msgs: list[PacketArray]) -> None:
        """Localize the packets of several PacketArrays (bad packets counted one by one)."""
        views = []
        for msg in msgs:
            self.frame_id = msg.header.frame_id
            self.last_upstream = (msg.packets_dropped, msg.frames_bad_crc)
            for p in msg.packets:
                self._account_sequence(int(p.sequence_id))
                try:
                    x = packet_samples(p)
                except ValueError as exc:
                    self.counts["packets"] += 1
                    self.counts["rejected_MALFORMED_inconsistent"] += 1
                    self.get_logger().warning(str(exc), throttle_duration_sec=5.0)
                    continue
                views.append(
                    PacketView(
                        x,
                        p.sample_rate_hz,
                        p.onset_index,
                        time_msg_to_ns(p.stamp),
                        p.sequence_id,
                        p.noise_rms_v,
                        p.saturated,
                    )
                )
        self.pipeline.process(views, self._publish)

    def _publish(self, records) -> None:
        for rec in records:
            ev = emission_msg(emission_record(rec), self.frame_id)
            self.pub_events.publish(ev)
            self.counts["published_events"] += 1
            if self.p["markers"]:
                self.events.add(ev, self.get_clock().now().nanoseconds)

    # ------------------------------------------------------------------ outputs
    def publish_markers(self) -> None:
        if (
            not self.frame_id
            or not self.p["markers"]
            or self.pub_markers.get_subscription_count() == 0
        ):
            return
        now = self.get_clock().now()
        stamp = now.to_msg()
        arr = sensor_markers(self.geometry, self.frame_id, stamp)
        self.events.frame_id = self.frame_id
        arr.markers.extend(self.events.render(now.nanoseconds, stamp).markers)
        self.pub_markers.publish(arr)

    def publish_diagnostics(self) -> None:
        st = pipeline_statuses(
            self.get_fully_qualified_name(),
            self.hardware_id,
            self.pipeline,
            None,
            self.counts["published_events"],
            0,
        )
        st[0].values += [
            KeyValue(key="upstream_packets_dropped", value=str(self.last_upstream[0])),
            KeyValue(key="upstream_frames_bad_crc", value=str(self.last_upstream[1])),
        ]
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = st
        self.pub_diag.publish(msg)


def main(args=None) -> int:
    return run_node(LocalizerNode, args)


if __name__ == "__main__":
    sys.exit(main())
