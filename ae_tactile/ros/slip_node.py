# SPDX-License-Identifier: Apache-2.0
"""`slip_detector` node: localized emissions -> contacts, slip events, readings, state.

The replay half of the velodyne-style split (the driver runs the same stage in-process by
default): feeds the localizer's emissions (Emission on `localized`) to the core
`ae_tactile.pipeline.SlipStage` and publishes what the driver would: `contacts`
(ContactEvent TOUCH when a contact begins, DETOUCH when it ends, with its id), `slip`
(SLIP_PRECURSOR / SLIP / TEXTURE of a contact), `emissions` (each emission with its
reading and contact id), the finger's latched `contact_state` (ContactState with the
current contacts, transient local: a hand controller can read it at any time), markers
and /diagnostics. The sliding speed for TEXTURE spatial
periods comes from the `slip.sliding_speed_m_s` parameter or the `sliding_speed` topic
(std_msgs/Float64, m/s). Every field of `SlipConfig` is a parameter `slip.<field>`
(docs/slip.md); the run-time ones can be changed with `ros2 param set`.

Late events: events arriving out of order are processed with their own stamps up to
`slip.reorder_tolerance_s` behind the newest one; the time-keeping tick never moves the
detector's clock past now - `lag_s`; events dropped for being older are counted in
/diagnostics.
"""

from __future__ import annotations

import math
import sys

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from std_msgs.msg import Float64
from visualization_msgs.msg import MarkerArray

from ae_tactile.msg import ContactEvent, ContactState, Emission
from ae_tactile.pipeline import EventType, SlipStage
from ae_tactile.ros.conversions import (
    contact_event_msg,
    contact_record_of_emission,
    contact_state_msg,
    emission_msg,
)
from ae_tactile.ros.diagnostics import pipeline_statuses
from ae_tactile.ros.driver_params import EMISSION_QOS, EVENT_QOS
from ae_tactile.ros.markers import EventMarkers, contact_markers
from ae_tactile.ros.node_utils import LATCHED, run_node
from ae_tactile.ros.params import (
    Param,
    ParameterError,
    ParamSet,
    declare,
    slip_config_kwargs,
    slip_params,
    tunable,
)
from ae_tactile.slip import SlipConfig

NODE_PARAMS = [
    Param(
        "lag_s",
        0.02,
        "The time-keeping tick never moves the detector's clock past now minus "
        "this, so events still in flight are not overtaken",
        0.0,
        1.0,
    ),
    Param("tick_period_s", 0.02, "Period of the time-keeping tick", 0.001, 1.0),
    Param("marker_period_s", 0.1, "Marker refresh period", 0.02, 5.0),
    Param("frame_id", "", "Frame of the outputs; empty = the incoming events' frame"),
    tunable(Param("markers", True, "Publish slip markers on 'markers' (only while subscribed)")),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics messages", 0.05, 60.0),
    Param(
        "wait_for_subscribers",
        0,
        "Subscribe to 'localized' only once this many subscribers are matched on 'contacts' "
        "(the hand), so that in a managed start no first TOUCH is published before its "
        "consumer listens (0: at once)",
        0,
        100,
    ),
]


class SlipDetectorNode(Node):
    def __init__(self, **kwargs):
        super().__init__("slip_detector", **kwargs)
        self.p = declare(self, NODE_PARAMS)
        self.slip_params = ParamSet(self, slip_params(), "slip.", on_change=self._on_slip_change)
        try:
            config = SlipConfig(**slip_config_kwargs(self.slip_params.values))
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"slip detector parameters: {exc}") from exc
        self.stage = SlipStage(config, lag_s=self.p["lag_s"])
        self.detector = self.stage.detector
        self.pub_contacts = self.create_publisher(ContactEvent, "contacts", EVENT_QOS)
        self.pub_slip = self.create_publisher(ContactEvent, "slip", EVENT_QOS)
        self.pub_emissions = self.create_publisher(Emission, "emissions", EMISSION_QOS)
        self.pub_state = self.create_publisher(ContactState, "contact_state", LATCHED)
        self.pub_markers = self.create_publisher(MarkerArray, "markers", 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.markers = EventMarkers("", 2.0, namespace="ae_tactile/slip")
        if self.p["wait_for_subscribers"] > 0:
            self._subscribe_timer = self.create_timer(0.01, self._subscribe_when_matched)
        else:
            self._subscribe_localized()
        self.create_subscription(Float64, "sliding_speed", self.on_speed, 10)
        self.create_timer(self.p["tick_period_s"], self.tick)
        self.create_timer(self.p["marker_period_s"], self.publish_markers)
        self.create_timer(self.p["diagnostics_period_s"], self.publish_diagnostics)
        self.frame_id = self.p["frame_id"]
        self.last_state_key = None
        self.last_state_pub_ns = 0
        self.published = 0  # slip events
        self.published_contacts = 0
        self.published_emissions = 0
        self.received = 0
        self.publish_state(force=True)

    def _subscribe_localized(self) -> None:
        self.create_subscription(Emission, "localized", self.on_emission, EMISSION_QOS)
        self.get_logger().info("slip_detector: listening on 'localized'")

    def _subscribe_when_matched(self) -> None:
        """A managed start (the split launch's chain): the localizer waits for this node on
        `localized`, the driver for the localizer on `packets`; `contacts` keeps no history
        for late joiners, so this node listens only once its consumers do."""
        if self.pub_contacts.get_subscription_count() >= self.p["wait_for_subscribers"]:
            self._subscribe_timer.cancel()
            self._subscribe_localized()

    def _on_slip_change(self, changes: dict) -> None:
        values = dict(self.slip_params.values, **changes)
        config = SlipConfig(**slip_config_kwargs(values))  # ValueError rejects the change
        with self.stage.lock:
            update = getattr(self.stage.detector, "update_config", None)
            if update is not None:
                update(**{k: getattr(config, k) for k in changes})
            else:
                self.stage.detector.config = config

    def on_speed(self, msg: Float64) -> None:
        v = float(msg.data)
        try:
            with self.stage.lock:
                self.detector.set_sliding_speed(v if v > 0 and math.isfinite(v) else None)
        except ValueError as exc:
            self.get_logger().warning(
                f"sliding_speed {v} ignored: {exc}", throttle_duration_sec=5.0
            )

    def on_emission(self, msg: Emission) -> None:
        self.received += 1
        if not self.frame_id:
            self.frame_id = msg.header.frame_id
        try:
            rec = contact_record_of_emission(msg)
        except (TypeError, ValueError):
            self.stage.counts["rejected_invalid_emission"] += 1
            return
        emissions: list = []
        self._publish(self.stage.process([rec], emissions))
        for e in emissions:
            out = emission_msg(e, self.frame_id)
            self.pub_emissions.publish(out)
            self.published_emissions += 1
            if self.p["markers"]:
                self.markers.add(out, self.get_clock().now().nanoseconds)
        self.publish_state()

    def _publish(self, records) -> None:
        """A contact's TOUCH / DETOUCH on `contacts`, its slip events on `slip`."""
        for r in records:
            ev = contact_event_msg(r, self.frame_id)
            if r.event_type in (EventType.TOUCH, EventType.DETOUCH):
                self.pub_contacts.publish(ev)
                self.published_contacts += 1
            else:
                self.pub_slip.publish(ev)
                self.published += 1
            if self.p["markers"]:
                self.markers.add(ev, self.get_clock().now().nanoseconds)

    def tick(self) -> None:
        self.stage.tick(self.get_clock().now().nanoseconds)
        self._publish(self.stage.pop_events())  # contacts whose release was confirmed
        self.publish_state()

    def publish_markers(self) -> None:
        if self.frame_id and self.markers.events and self.pub_markers.get_subscription_count():
            now = self.get_clock().now()
            self.markers.frame_id = self.frame_id
            arr = self.markers.render(now.nanoseconds, now.to_msg())
            arr.markers.extend(contact_markers(self.stage.contacts, self.frame_id, now.to_msg(),
                                               3.0 * self.p["marker_period_s"]).markers)
            self.pub_markers.publish(arr)

    def publish_state(self, force: bool = False) -> None:
        st = self.stage.state
        key = (int(st.state), int(st.since_ns), int(st.contact_id), self.stage.contacts_key())
        now = self.get_clock().now().nanoseconds
        if (
            not force
            and key == self.last_state_key
            and now - self.last_state_pub_ns < 1_000_000_000
        ):
            return
        self.last_state_key, self.last_state_pub_ns = key, now
        self.pub_state.publish(contact_state_msg(st, self.frame_id, now, self.stage.contacts))

    def publish_diagnostics(self) -> None:
        statuses = pipeline_statuses(
            self.get_fully_qualified_name(),
            self.frame_id or "fingertip",
            None,
            self.stage,
            self.published_contacts,
            self.published,
            self.published_emissions,
        )
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = statuses
        self.pub_diag.publish(msg)


def main(args=None) -> int:
    return run_node(SlipDetectorNode, args)


if __name__ == "__main__":
    sys.exit(main())
