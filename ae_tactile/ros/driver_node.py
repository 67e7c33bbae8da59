# SPDX-License-Identifier: Apache-2.0
"""`driver` node: the fingertip from serial bytes to contact and slip events, in one process.

The hot path runs in the serial reader thread, with no message hop between stages: the link
(`ae_tactile.link`) decodes frames and hands each batch of packets to the core pipeline
(`ae_tactile.pipeline`: validation, interference rejection, localization, the slip
detector's interpretation), and this node publishes what comes out at once: a contact's
begin / end first, then slip events, the emissions with their readings and the contact
state, then (only when someone subscribes or records) the raw packets. With
``pipeline:=false`` it publishes raw packets only, for the separate `localizer` and
`slip_detector` nodes (replaying bags, velodyne-style: same core code).

From the read callback to the publish call (three files): the link's reader thread calls
`DriverNode._on_batch` (this file) -> `ContactPipeline.process` (`pipeline/core.py`, which
calls the stages in order) -> `DriverNode._publish_contacts` / `_publish_slip` /
`_publish_emissions` -> `ContactEventWire.encode` / `EmissionWire.encode`
(`conversions.py`) -> ``Publisher.publish``.

Acquisition starts once the pipeline is ready (compiled, geometry known) and, with
``wait_for_subscribers:=N``, once N subscribers are matched on ``contacts`` or on
``packets`` (``packets`` only without the pipeline): no first event is lost.

Topics (relative, so a namespace per finger works):
  contacts      ae_tactile/ContactEvent  TOUCH when a contact begins, DETOUCH when it ends
                                         (with its contact_id), reliable, depth 100
  slip          ae_tactile/ContactEvent  SLIP_PRECURSOR / SLIP / TEXTURE of a contact,
                                         reliable, depth 100
  emissions     ae_tactile/Emission      every localized emission with its reading (touch,
                                         release, micro-slip, slip, texture, unknown) and
                                         contact_id, reliable, depth 1000
  contact_state ae_tactile/ContactState  the finger's state and its current contacts,
                                         latched (transient local, depth 1)
  markers       visualization_msgs/MarkerArray  when subscribed
  packets       ae_tactile/PacketArray   sensor-data QoS, or reliable with reliable_qos:=true
                                         (for `ros2 bag record`); only when subscribed
  sensor_info   ae_tactile/SensorInfo    latched (bags self-describing)
  /diagnostics  diagnostic_msgs/DiagnosticArray  link, localization and slip status
Subscribes: sliding_speed (std_msgs/Float64, m/s; TEXTURE spatial periods),
  sim/scene_truth (the simulated fingertip's body: a mismatch with the parameters is warned
  about once and the device's body is used).
The fingertips of one hand (``hand_coincidence_topic``, e.g. /hand/apex_packets, the same
  for each): ae_tactile/ApexPackets published and read there; an apex packet that no test
  of one packet can tell from interference is held ``hand_coincidence_wait_s`` and
  dropped if another fingertip saw an apex packet within ``hand_coincidence_window_s``
  (docs/interference.md, "Across a hand").
"""

from __future__ import annotations

import gc
import json
import logging
import math
import sys
import time
from collections import deque

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from std_msgs.msg import Float64, String
from visualization_msgs.msg import MarkerArray

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.link import FingertipLink
from ae_tactile.msg import (
    ApexPackets,
    ContactEvent,
    ContactState,
    Emission,
    PacketArray,
    SensorInfo,
)
from ae_tactile.pipeline import ContactPipeline, SlipStage
from ae_tactile.pipeline.device_calibration import DeviceCalibration
from ae_tactile.ros.conversions import (
    ContactEventWire,
    ContactStateWire,
    EmissionWire,
    contact_event_msg,
    emission_msg,
    ns_to_time_msg,
    packet_array_msgs,
    sensor_info_msg,
)
from ae_tactile.ros.diagnostics import link_rates, link_status, pipeline_statuses
from ae_tactile.ros.driver_params import (  # noqa: F401  (DRIVER_PARAMS, EVENT_QOS: public here too)
    DRIVER_PARAMS,
    EMISSION_QOS,
    EVENT_QOS,
    detector_options,
    geometry_from_params,
    link_config_from_params,
    packet_qos,
)
from ae_tactile.ros.markers import EventMarkers, contact_markers, sensor_markers
from ae_tactile.ros.node_utils import (
    LATCHED,
    cpu_list,
    events_executor,
    pin_process,
    run_node,
)
from ae_tactile.ros.params import (
    LOCALIZATION_PARAMS,
    ParameterError,
    ParamSet,
    changes_for_localizer,
    make_packet_localizer,
    slip_config_kwargs,
    slip_params,
    warn_unknown_parameters,
)
from ae_tactile.slip import SlipConfig

#: Name of the executable (`ros2 run ae_tactile driver`), for ``--help``.
EXECUTABLE = "driver"
#: The node's parameters as it declares them, (prefix, table), for ``--help``.
NODE_PARAMETERS = [
    ("", "DRIVER_PARAMS"),
    ("localization.", "ae_tactile.ros.params:LOCALIZATION_PARAMS"),
    ("slip.", "ae_tactile.ros.params:slip_params"),
]


def _pipeline_names() -> list[str]:
    """Full names of the in-process pipeline's parameters (declared with pipeline:=true)."""
    return [
        prefix + p.name
        for prefix, table in (("localization.", LOCALIZATION_PARAMS), ("slip.", slip_params()))
        for p in table
    ]


class DriverNode(Node):
    def __init__(self, **kwargs):
        super().__init__("driver", **kwargs)
        self.params = ParamSet(self, DRIVER_PARAMS, on_change=self._on_driver_change)
        p = self.p = self.params.values
        if p["cpu_affinity"].strip():
            try:
                pin_process(cpu_list(p["cpu_affinity"]))
            except OSError as exc:
                raise ParameterError(
                    f"parameter 'cpu_affinity' = {p['cpu_affinity']!r}: this process may not "
                    f"run there ({exc.strerror})"
                ) from exc
        self.link_config = link_config_from_params(p)
        self.frame_id = p["frame_id"]
        self.pub_packets = self.create_publisher(
            PacketArray, "packets", packet_qos(p["reliable_qos"])
        )
        self.pub_info = self.create_publisher(SensorInfo, "sensor_info", LATCHED)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._info_key = None
        self._last_diag = None
        self.published_packets = 0
        self.published_events = 0
        self.published_slip = 0
        self.published_emissions = 0
        self.scene_body = None
        self._body_warned = False
        try:
            self.geometry = geometry_from_params(p)
        except ValueError as exc:
            raise ParameterError(f"fingertip geometry: {exc}") from exc
        self.pipeline = None
        if p["hand_coincidence_topic"] and not p["pipeline"]:
            raise ParameterError(
                f"parameter 'hand_coincidence_topic' = {p['hand_coincidence_topic']!r} needs "
                "pipeline:=true (the hand's test runs in the driver's pipeline)"
            )
        self.calibration = None
        if p["pipeline"]:
            self._make_pipeline()
        self.create_subscription(String, "sim/scene_truth", self._on_scene_truth, LATCHED)
        # the pipeline's names, in a parameter file shared with pipeline:=true, are known
        warn_unknown_parameters(self, known=[] if p["pipeline"] else _pipeline_names())
        self.now_ns = self._clock_ns()
        self.link = FingertipLink(
            self.link_config,
            clock_ns=self.now_ns,
            sink=self._on_batch,
            on_idle=self._on_link_idle,
            logger=logging.getLogger("ae_tactile.link"),
        )
        self.create_timer(p["diagnostics_period_s"], self._publish_diagnostics)
        self._publish_sensor_info()
        if self.pipeline is not None:
            fs = float(p["sample_rate_hz"] or 10e6)
            self.get_logger().info(
                "warming up the pipeline before START (1-2 s; about a minute on the first "
                "start after an install that did not run `python -m ae_tactile.compile_kernels`)"
            )
            self.pipeline.localizer.warm_up(fs, int(p["packet_samples"] or 400))
            if self.pipeline.localizer.resolve_overlaps:
                self.pipeline.overlap_stage.reader_backlog = self.link.unread_bytes  # late check
                self.pipeline.start_overlaps(wait_s=30.0)
        # Everything built so far lives for the whole run: keep it out of the garbage
        # collector's scans, so that a collection in the reader thread stays short.
        gc.collect()
        gc.freeze()
        if p["wait_for_subscribers"] > 0:
            self._start_timer = self.create_timer(0.01, self._start_when_subscribed)
        else:
            self.link.start()
        self.get_logger().info(
            f"driver on {self.link_config.port} ({self.link_config.mode} mode), "
            f"frame '{self.frame_id}', "
            + (
                f"in-process pipeline ({self.pipeline.localizer.method})"
                if self.pipeline
                else "raw packets only"
            )
        )

    def _clock_ns(self):
        """Host clock for stamps: ROS time; without simulated time that is the system clock,
        read directly (time.time_ns, ~0.1 us instead of ~20 us through rclpy)."""
        use_sim = self.has_parameter("use_sim_time") and self.get_parameter("use_sim_time").value
        if not use_sim:
            return time.time_ns
        return lambda: self.get_clock().now().nanoseconds

    # -------------------------------------------------------------- pipeline
    def _make_pipeline(self) -> None:
        self.loc_params = ParamSet(
            self, LOCALIZATION_PARAMS, "localization.", on_change=self._on_localization_change
        )
        self.slip_params = ParamSet(self, slip_params(), "slip.", on_change=self._on_slip_change)
        lp = self.loc_params.values
        try:
            slip_config = SlipConfig(**slip_config_kwargs(self.slip_params.values))
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"slip parameters: {exc}") from exc
        localizer = make_packet_localizer(
            lp, geometry=self.geometry, channel_gains=self.p["channel_gains"]
        )
        self.slip_stage = SlipStage(slip_config, lag_s=self.p["slip_lag_s"])
        self.pipeline = ContactPipeline(localizer, self.slip_stage)
        self.pipeline.overlap_inline_max = int(lp["overlap_inline_max"])
        # on cores of its own, the overlap resolver yields to the reader at once
        self.pipeline.overlap_idle = bool(self.p["cpu_affinity"].strip())
        self.pub_contacts = self.create_publisher(ContactEvent, "contacts", EVENT_QOS)
        self.pub_slip = self.create_publisher(ContactEvent, "slip", EVENT_QOS)
        self.pub_emissions = self.create_publisher(Emission, "emissions", EMISSION_QOS)
        self.pub_state = self.create_publisher(ContactState, "contact_state", LATCHED)
        self.pub_markers = self.create_publisher(MarkerArray, "markers", 10)
        self.markers = EventMarkers(self.frame_id, self.p["marker_lifetime_s"])
        self._marker_inbox: deque = deque(maxlen=64)  # ContactRecords not drawn yet
        self._wire = ContactEventWire(self.frame_id)
        self._emission_wire = EmissionWire(self.frame_id)
        self._state_wire = ContactStateWire(self.frame_id)
        # a DETOUCH decided by the timer's tick (a release confirmed) goes out there too
        self.pipeline.set_outputs(None, self._publish_slip, on_contacts=self._publish_contacts,
                                  on_emissions=self._publish_emissions)
        self._state_key = None
        self._state_pub_ns = 0
        self.create_subscription(Float64, "sliding_speed", self._on_sliding_speed, 10)
        self.pub_apex = None
        if self.p["hand_coincidence_topic"]:
            try:
                self.pipeline.enable_hand(
                    self.p["hand_coincidence_window_s"], self.p["hand_coincidence_wait_s"]
                )
            except ValueError as exc:
                raise ParameterError(f"hand coincidence: {exc}") from exc
            topic = self.p["hand_coincidence_topic"]
            self._fqn = self.get_fully_qualified_name()  # this fingertip, on the hand's topic
            self.pub_apex = self.create_publisher(ApexPackets, topic, EVENT_QOS)
            self.pipeline.on_apex = self._report_apex
            self.create_subscription(ApexPackets, topic, self._on_hand_apex, EVENT_QOS)
        self.create_timer(self.p["slip_tick_period_s"], self._tick)
        if self.p["calibration_dir"].strip().lower() != "none":
            self.calibration = DeviceCalibration(
                self.pipeline.calibration_learners, self.p["calibration_dir"].strip(),
                self.p["calibration_reset"], self.p["calibration_save_period_s"],
                body=lambda: self.pipeline.localizer.geometry)
        self.create_timer(self.p["marker_period_s"], self._publish_markers)

    def _on_batch(self, batch) -> None:
        """Reader thread: one decoded batch -> events, published at once."""
        if self.calibration is not None:  # the device's own models, once it is known
            self.calibration.on_device(self.hardware_id(serial_only=True))
        if self.pipeline is not None:
            self.pipeline.process(
                batch.packets,
                None,
                self._publish_slip,
                more_waiting=self.link.bytes_waiting,
                on_contacts=self._publish_contacts,
                on_emissions=self._publish_emissions,
            )
            if self.pub_apex is not None:
                self._hand_step()
            self._publish_state()
        if self.pub_packets.get_subscription_count() > 0:
            for msg in packet_array_msgs(batch, self.frame_id):
                self.pub_packets.publish(msg)
            self.published_packets += len(batch.packets)

    def _on_link_idle(self) -> None:
        """Reader thread, nothing more to read: the hand's held packets, the echo test's
        learning."""
        if self.pipeline is None:
            return
        if self.pub_apex is not None and self._hand_step():
            self._publish_state()
        if self.pipeline.run_idle_work():
            self._publish_state()
        if self.calibration is not None:
            self.calibration.save_due()

    def _report_apex(self) -> None:
        """Reader thread: report this fingertip's apex packets to the hand (called by the
        pipeline before its slip step, and after each batch)."""
        onsets = self.pipeline.take_apex_onsets()
        if onsets:
            msg = ApexPackets()
            msg.header.stamp = ns_to_time_msg(self.now_ns())
            msg.header.frame_id = self.frame_id
            msg.fingertip = self._fqn
            msg.onset_ns = onsets
            self.pub_apex.publish(msg)

    def _hand_step(self) -> bool:
        """Reader thread: report this fingertip's apex packets to the hand, and hand out
        the held ones whose wait is over (True if any)."""
        self._report_apex()
        return self.pipeline.release_coincidence(self.now_ns())

    def _on_hand_apex(self, msg: ApexPackets) -> None:
        if msg.fingertip != self._fqn:
            self.pipeline.hand_reports(msg.onset_ns, msg.fingertip, self.now_ns())

    def _publish_contacts(self, records) -> None:
        encode, publish = self._wire.encode, self.pub_contacts.publish
        for r in records:
            publish(encode(r))  # the serialized message: no Python message on the hot path
        self._marker_inbox.extend(records)  # markers are drawn from the records, later
        self.published_events += len(records)

    def _publish_slip(self, records) -> None:
        encode, publish = self._wire.encode, self.pub_slip.publish
        for r in records:
            publish(encode(r))
        self._marker_inbox.extend(records)
        self.published_slip += len(records)

    def _publish_emissions(self, records) -> None:
        encode, publish = self._emission_wire.encode, self.pub_emissions.publish
        for r in records:
            publish(encode(r))
        self._marker_inbox.extend(records)
        self.published_emissions += len(records)

    def _publish_state(self, force: bool = False, contacts_now: bool = False) -> None:
        """ContactState when the finger's state changed (at once), when only its contacts
        changed (``contacts_now``: the timer, every slip_tick_period_s; the reader thread
        leaves that to it: a TOUCH already told the hand, and listing the contacts costs
        the next packet's latency), and once a second."""
        st = self.slip_stage.state
        contacts = self.slip_stage.contacts_key()
        key = (int(st.state), int(st.since_ns), int(st.contact_id), contacts)
        now = self.now_ns()
        old = self._state_key
        if not force and now - self._state_pub_ns < 1_000_000_000 and (
            key == old or (not contacts_now and old is not None and key[:3] == old[:3])
        ):
            return
        self._state_key, self._state_pub_ns = key, now
        self.pub_state.publish(self._state_wire.encode(st, now, self.slip_stage.contacts))

    def _tick(self) -> None:
        if self.pipeline is not None:
            self.pipeline.release_held()  # slip steps whose wait for the resolver expired
            if self.pub_apex is not None:
                # the reader decides the hand's held packets within read_timeout_s; this is
                # for a reader that is not running (the link down): never beside it
                self.pipeline.release_coincidence(self.now_ns(), blocking=False)
            self.pipeline.tick(self.now_ns())
        else:
            self.slip_stage.tick(self.now_ns())
        self._publish_state(contacts_now=True)

    def _publish_markers(self) -> None:
        if not self.p["markers"] or self.pub_markers.get_subscription_count() == 0:
            self._marker_inbox.clear()
            return
        now = self.get_clock().now()
        while self._marker_inbox:
            rec = self._marker_inbox.popleft()
            msg = (emission_msg(rec, self.frame_id) if hasattr(rec, "reading")
                   else contact_event_msg(rec, self.frame_id))
            self.markers.add(msg, now.nanoseconds)
        stamp = now.to_msg()
        arr = sensor_markers(self.geometry, self.frame_id, stamp)
        arr.markers.extend(self.markers.render(now.nanoseconds, stamp).markers)
        arr.markers.extend(contact_markers(self.slip_stage.contacts, self.frame_id, stamp,
                                           3.0 * self.p["marker_period_s"]).markers)
        self.pub_markers.publish(arr)

    def _on_sliding_speed(self, msg: Float64) -> None:
        v = float(msg.data)
        try:
            with self.slip_stage.lock:
                self.slip_stage.detector.set_sliding_speed(
                    v if v > 0 and math.isfinite(v) else None
                )
        except ValueError as exc:
            self.get_logger().warning(
                f"sliding_speed {v} ignored: {exc}", throttle_duration_sec=5.0
            )

    # -------------------------------------------------------------- run-time parameters
    def _on_driver_change(self, changes: dict) -> None:
        """Tunable driver parameters: markers is read where it is used; the hand's window
        and wait apply at once (ValueError: a wait below the window)."""
        hand = {k: changes[k] for k in changes if k.startswith("hand_coincidence_")}
        if hand and self.pipeline is not None and self.pipeline.hand is not None:
            values = dict(self.p, **changes)
            self.pipeline.enable_hand(
                values["hand_coincidence_window_s"], values["hand_coincidence_wait_s"]
            )
            self.get_logger().info(f"hand coincidence changed: {hand}")

    def _on_localization_change(self, changes: dict) -> None:
        self.pipeline.localizer.update(**changes_for_localizer(changes))
        if "reject_interference" in changes:
            self.pipeline.localizer.set_interference(changes["reject_interference"])
        if "overlap_inline_max" in changes:
            self.pipeline.overlap_inline_max = int(changes["overlap_inline_max"])
        if changes.get("resolve_overlaps"):
            self.pipeline.start_overlaps()  # its worker starts now, not on the hot path
        self.get_logger().info(f"localization parameters changed: {changes}")

    def _on_slip_change(self, changes: dict) -> None:
        values = dict(self.slip_params.values, **changes)
        config = SlipConfig(**slip_config_kwargs(values))  # ValueError rejects the change
        with self.slip_stage.lock:
            det = self.slip_stage.detector
            update = getattr(det, "update_config", None)
            if update is not None:
                update(**{k: config.__getattribute__(k) for k in changes})
            else:
                det.config = config
        self.get_logger().info(f"slip parameters changed: {changes}")

    # -------------------------------------------------------------- start
    #: [s] once enough subscribers are matched on `contacts`, how long acquisition waits for
    #: as many on `emissions` (a consumer of both, e.g. the monitor, is discovered topic by
    #: topic; one of `contacts` alone starts this much later)
    EMISSIONS_GRACE_S = 0.5

    def _start_when_subscribed(self) -> None:
        need = self.p["wait_for_subscribers"]
        matched = self.pub_packets.get_subscription_count()
        if self.pipeline is not None:
            matched = max(matched, self.pub_contacts.get_subscription_count())
            if matched >= need and self.pub_emissions.get_subscription_count() < need:
                now = time.monotonic()
                self._matched_at = getattr(self, "_matched_at", None) or now
                if now - self._matched_at < self.EMISSIONS_GRACE_S:
                    return
        if matched >= need:
            self._start_timer.cancel()
            self.link.start()

    def _on_scene_truth(self, msg: String) -> None:
        """The simulated fingertip's body: it wins over the parameters (warned once)."""
        try:
            body = json.loads(msg.data).get("sensor")
        except ValueError:
            return
        if not body or self.scene_body == body:
            return
        self.scene_body = body
        try:
            geo = FingertipGeometry(
                float(body["radius_m"]),
                float(body["element_offset_m"]),
                float(body["sound_speed_m_s"]),
            )
        except (KeyError, TypeError, ValueError):
            return
        mine = self.geometry
        differs = (
            body.get("medium") != self.p["medium"]
            or not math.isclose(geo.radius_m, mine.radius_m, rel_tol=1e-3)
            or not math.isclose(geo.element_offset_m, mine.element_offset_m, rel_tol=1e-3)
            or not math.isclose(geo.sound_speed_m_s, mine.sound_speed_m_s, rel_tol=1e-3)
        )
        if not differs:
            return
        if not self._body_warned:
            self._body_warned = True
            self.get_logger().warning(
                f"the fingertip reports {body.get('medium')} (R={geo.radius_m * 1e3:.2f} mm, "
                f"a={geo.element_offset_m * 1e3:.2f} mm, c={geo.sound_speed_m_s:.0f} m/s) but the "
                f"parameters say {self.p['medium']} (R={mine.radius_m * 1e3:.2f} mm, "
                f"a={mine.element_offset_m * 1e3:.2f} mm, c={mine.sound_speed_m_s:.0f} m/s): "
                "using the fingertip's; fix the parameter file (config/water_skin.yaml or "
                "config/silicone.yaml)"
            )
        self.geometry = geo
        self.p["medium"] = str(body.get("medium", self.p["medium"]))
        self.p["radius_m"], self.p["element_offset_m"] = geo.radius_m, geo.element_offset_m
        self.p["sound_speed_m_s"] = geo.sound_speed_m_s
        if self.pipeline is not None:
            self.pipeline.localizer.update(geometry=geo)
        self._info_key = None
        self._publish_sensor_info()

    # -------------------------------------------------------------- sensor info
    def _publish_sensor_info(self) -> None:
        """Latched SensorInfo, re-published only when the device's identity or settings change."""
        st = self.link.device_status
        key = (
            ("no device",)
            if st is None
            else (
                st.serial_number,
                st.firmware_version,
                st.sample_rate_hz,
                st.v_per_count,
                st.threshold_counts,
            )
        )
        if key == self._info_key:
            return
        self._info_key = key
        self.pub_info.publish(sensor_info_msg(
            st, self.p, self.geometry, self.frame_id, self.get_clock().now().to_msg()))

    # -------------------------------------------------------------- diagnostics
    def hardware_id(self, serial_only: bool = False) -> str | None:
        """The device's serial number (its STATUS); before it is known, the port (None
        with ``serial_only``)."""
        st = self.link.device_status
        if st is not None and st.serial_number:
            return st.serial_number
        return None if serial_only else self.link_config.port

    def _publish_diagnostics(self) -> None:
        self._publish_sensor_info()
        s = self.link.stats()
        now = self.get_clock().now().nanoseconds
        rates = link_rates(s, self._last_diag, now)
        self._last_diag = (now, s)
        name, hw = self.get_fully_qualified_name(), self.hardware_id()
        statuses = [link_status(name, hw, s, rates, self.published_packets)]
        if self.pipeline is not None:
            statuses += pipeline_statuses(
                name, hw, self.pipeline, self.slip_stage, self.published_events,
                self.published_slip, self.published_emissions,
                calibration=self.calibration.status() if self.calibration else None,
            )
        msg = DiagnosticArray()
        msg.header.stamp = ns_to_time_msg(now)
        msg.status = statuses
        self.pub_diag.publish(msg)

    def destroy_node(self):
        if hasattr(self, "link") and self.link._thread is not None:
            self.link.stop()
        if getattr(self, "calibration", None) is not None:
            self.calibration.close()  # the reader has stopped: the learners are still
        if getattr(self, "pipeline", None) is not None:
            if getattr(self, "pub_apex", None) is not None:
                # the apex touches the hand still holds: decided with the reports at hand
                # (not waiting long for a reader that did not stop)
                problem = None
                try:
                    self.pipeline.release_coincidence(self.now_ns(), flush=True, timeout_s=1.0)
                except Exception as exc:  # noqa: BLE001 (the context may be gone already)
                    problem = repr(exc)
                hand = self.pipeline.hand
                if problem is None and hand is not None and hand.pending:
                    problem = f"{hand.pending} still held (the reader did not stop)"
                if problem is not None:
                    print(f"[ae_tactile] driver: held apex packets not handed out at "
                          f"shutdown: {problem}", flush=True)
            self.pipeline.close()
        return super().destroy_node()


def main(args=None) -> int:
    sys.setswitchinterval(0.0005)  # the reader thread gets the GIL back quickly
    return run_node(DriverNode, args, executor_factory=events_executor)


if __name__ == "__main__":
    sys.exit(main())
