"""`driver` node: fingertip serial link -> PacketArray, diagnostics, latched SensorInfo.

Publishes only raw packets (the localizer interprets them), like velodyne's driver.
All link work (reading, decoding, reconnecting, time mapping, stream-mode packet
cutting) is in the core (`ae_tactile.link`); this node declares parameters, converts
batches to messages and publishes them as soon as the reader thread hands them over:
a publisher thread blocks on the link's bounded queue (rclpy publishers are
thread-safe), so packets neither wait for an executor wake-up nor pay its overhead;
the executor only runs the diagnostics timer.

Topics (relative, so a namespace per finger works):
  packets      ae_tactile/PacketArray   sensor-data QoS (best effort), or reliable with
                                        reliable_qos:=true (for `ros2 bag record`)
  sensor_info  ae_tactile/SensorInfo    transient-local, depth 1 (bags self-describing)
  /diagnostics diagnostic_msgs/DiagnosticArray  at diagnostics_period_s
"""
from __future__ import annotations

import sys
import threading

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from ae_tactile.geometry import MEDIA
from ae_tactile.link import MODES, FingertipLink, LinkConfig
from ae_tactile.msg import PacketArray, SensorInfo
from ae_tactile.ros.conversions import make_packet, ns_to_time_msg
from ae_tactile.ros.node_utils import LATCHED, run_node
from ae_tactile.ros.params import Param, ParameterError, declare

DRIVER_PARAMS = [
    Param("port", "/dev/ttyACM0", "Serial device path or pyserial URL (socket://host:port, loop://, a pty path)",
          check=lambda v: None if isinstance(v, str) and v.strip() else "must be a non-empty string"),
    Param("baudrate", 3_000_000, "Serial baud rate (bit/s); ignored by USB CDC, ptys and sockets", 50, 100_000_000),
    Param("frame_id", "ae_tactile_fingertip", "TF frame of the fingertip (origin at the sphere centre, +z to the apex)",
          check=lambda v: None if isinstance(v, str) and v.strip() else "must be a non-empty frame name"),
    Param("mode", "triggered", "Acquisition mode: 'triggered' (device cuts packets) or 'stream' (host cuts packets)",
          choices=MODES),
    Param("sample_rate_hz", 0, "ADC sample rate to set on the device (Hz); 0 keeps the device's", 0, 20_000_000),
    Param("threshold_counts", 0, "Device trigger threshold (ADC counts); 0 keeps the device's", 0, 32767),
    Param("packet_samples", 0, "Samples per channel of a triggered packet; 0 keeps the device's", 0, 8192),
    Param("pre_trigger_samples", 0, "Samples before the trigger in a packet; 0 = packet_samples/4", 0, 8191),
    Param("reliable_qos", False, "Publish packets reliably (for recording) instead of sensor-data QoS"),
    Param("queue_max_batches", 256, "Bound of the reader-to-publisher queue (overflow is counted as drops)", 1, 100_000),
    Param("link_timeout_s", 3.0, "Silence after which the link counts as lost (s); the device beats >= 1 Hz", 0.1, 60.0),
    Param("reconnect_max_s", 5.0, "Longest wait between reconnection attempts (s)", 0.1, 300.0),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics messages (s)", 0.05, 60.0),
    Param("wait_for_subscribers", 0, "Open the port only once 'packets' has this many subscribers "
          "(0: at once), so no packet is published before its consumers are matched", 0, 100),
    Param("detector_threshold_sigma", 6.0, "Stream mode: trigger threshold in noise sigmas", 2.0, 100.0),
    Param("medium", "water_skin", "Fingertip body for SensorInfo: 'water_skin', 'silicone' or a label"),
    Param("radius_m", 10e-3, "Sphere radius R (m)", 1e-3, 0.1),
    Param("element_offset_m", 1.5e-3, "PVDF element centre offset a (m): centres at (+-a, +-a, 0)", 1e-4, 0.02),
    Param("sound_speed_m_s", 0.0, "Sound speed c (m/s); 0 = the medium preset's", 0.0, 10_000.0),
    Param("channel_gains", [1.0, 1.0, 1.0, 1.0], "Relative gain of channels 0..3 (calibration)",
          check=lambda v: None if len(v) == 4 and all(g > 0 for g in v) else "needs 4 positive gains"),
    Param("highpass_hz", 100e3, "Analog front-end high-pass corner (Hz), for SensorInfo", 0.0, 5e6),
]


def packet_qos(reliable: bool) -> QoSProfile:
    """Sensor-data QoS (best effort, depth 5) or reliable depth 100 for recording."""
    if reliable:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    return qos_profile_sensor_data




def detector_options(p: dict) -> dict:
    """Stream-mode detector settings: threshold, and the geometry's wall-echo delay 2R/c
    and largest arrival spread over the elements 2 sqrt(2) a / c."""
    c = p["sound_speed_m_s"] or MEDIA.get(p["medium"], MEDIA["water_skin"])["sound_speed_m_s"]
    return {"threshold_sigma": p["detector_threshold_sigma"], "echo_delay_s": 2.0 * p["radius_m"] / c,
            "channel_spread_s": max(3e-6, 2.0 * 2 ** 0.5 * p["element_offset_m"] / c)}


def link_config_from_params(p: dict) -> LinkConfig:
    """LinkConfig from validated parameter values (0 = keep the device's setting)."""
    none0 = lambda v: None if v == 0 else int(v)   # noqa: E731
    packet_samples = none0(p["packet_samples"])
    pre = p["pre_trigger_samples"] if packet_samples else None
    if packet_samples and pre >= packet_samples:
        raise ParameterError(f"parameter 'pre_trigger_samples' = {pre} must be < packet_samples = {packet_samples}")
    try:
        return LinkConfig(port=p["port"].strip(), baudrate=p["baudrate"], mode=p["mode"],
                          sample_rate_hz=none0(p["sample_rate_hz"]),
                          threshold_counts=none0(p["threshold_counts"]),
                          packet_samples=packet_samples, pre_trigger_samples=pre or None,
                          queue_max_batches=p["queue_max_batches"], link_timeout_s=p["link_timeout_s"],
                          reconnect_max_s=max(p["reconnect_max_s"], 0.2),
                          detector=detector_options(p))
    except ValueError as exc:
        raise ParameterError(str(exc)) from exc


class DriverNode(Node):
    def __init__(self, **kwargs):
        super().__init__("driver", **kwargs)
        self.p = declare(self, DRIVER_PARAMS)
        self.link_config = link_config_from_params(self.p)
        self.pub_packets = self.create_publisher(PacketArray, "packets", packet_qos(self.p["reliable_qos"]))
        self.pub_info = self.create_publisher(SensorInfo, "sensor_info", LATCHED)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.link = FingertipLink(self.link_config, clock_ns=lambda: self.get_clock().now().nanoseconds)
        self._info_key = None
        self._last_diag = None
        self.published_packets = 0
        self.create_timer(self.p["diagnostics_period_s"], self._publish_diagnostics)
        self._publish_sensor_info()
        self._running = True
        self._publisher_thread = threading.Thread(target=self._publish_loop, name="ae_tactile_publisher",
                                                  daemon=True)
        self._publisher_thread.start()
        if self.p["wait_for_subscribers"] > 0:
            self._start_timer = self.create_timer(0.02, self._start_when_subscribed)
        else:
            self.link.start()
        self.get_logger().info(
            f"driver on {self.link_config.port} ({self.link_config.mode} mode), frame '{self.p['frame_id']}', "
            f"{'reliable' if self.p['reliable_qos'] else 'sensor-data'} QoS")

    def _start_when_subscribed(self) -> None:
        if self.pub_packets.get_subscription_count() >= self.p["wait_for_subscribers"]:
            self._start_timer.cancel()
            self.link.start()

    # -------------------------------------------------------------- packets
    def _publish_loop(self) -> None:
        while self._running:
            try:
                self._publish_batches(self.link.poll(timeout_s=0.1))
            except Exception as exc:   # never let the publisher thread die silently
                if self._running:
                    self.get_logger().error(f"publishing failed: {exc!r}")

    def _publish_batches(self, batches) -> None:
        for batch in batches:
            msg = PacketArray()
            msg.header.stamp = ns_to_time_msg(batch.receive_ns)
            msg.header.frame_id = self.p["frame_id"]
            msg.packets = [make_packet(r.samples_v, stamp_ns=r.stamp_ns, sample_rate_hz=r.sample_rate_hz,
                                       onset_index=r.onset_index, sequence_id=r.sequence_id,
                                       noise_rms_v=r.noise_rms_v, saturated=r.saturated)
                           for r in batch.packets]
            msg.packets_dropped = batch.packets_dropped
            msg.frames_bad_crc = batch.frames_bad_crc
            self.pub_packets.publish(msg)
            self.published_packets += len(batch.packets)

    # -------------------------------------------------------------- sensor info
    def _publish_sensor_info(self) -> None:
        st = self.link.device_status
        key = None if st is None else (st.serial_number, st.firmware_version, st.sample_rate_hz, st.v_per_count,
                                       st.threshold_counts)
        if self._info_key is not None and key == self._info_key:
            return
        self._info_key = key if key is not None else ("",)
        p = self.p
        msg = SensorInfo()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = p["frame_id"]
        msg.medium = p["medium"]
        msg.radius_m = p["radius_m"]
        msg.element_offset_m = p["element_offset_m"]
        preset = MEDIA.get(p["medium"], MEDIA["water_skin"])
        msg.sound_speed_m_s = p["sound_speed_m_s"] or preset["sound_speed_m_s"]
        msg.channel_gains = [float(g) for g in p["channel_gains"]]
        msg.highpass_hz = p["highpass_hz"]
        msg.adc_bits = 12
        from ae_tactile.protocol import PROTOCOL_VERSION
        msg.protocol_version = PROTOCOL_VERSION
        if st is not None:
            msg.serial_number = st.serial_number
            msg.firmware_version = ".".join(str(v) for v in st.firmware_version)
            msg.sample_rate_hz = float(st.sample_rate_hz)
            msg.volts_per_count = float(st.v_per_count)
            msg.trigger_threshold_v = float(st.threshold_counts * st.v_per_count)
        else:
            msg.sample_rate_hz = float(p["sample_rate_hz"])
        self.pub_info.publish(msg)

    # -------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        self._publish_sensor_info()
        s = self.link.stats()
        now = self.get_clock().now().nanoseconds
        rates = {}
        if self._last_diag is not None:
            t0, s0 = self._last_diag
            dt = max((now - t0) * 1e-9, 1e-9)
            rates = {"frame_rate_hz": (s["frames_ok"] - s0["frames_ok"]) / dt,
                     "packet_rate_hz": (s["packets_out"] - s0["packets_out"]) / dt}
        self._last_diag = (now, s)
        status = DiagnosticStatus()
        status.name = f"{self.get_fully_qualified_name()}: fingertip link"
        status.hardware_id = str(s.get("device_serial", self.link_config.port))
        if s["state"] != "connected":
            status.level, status.message = DiagnosticStatus.ERROR, f"link {s['state']}: {s['last_error']}"
        elif s["crc_errors"] or s["packets_dropped"] or s["header_errors"]:
            status.level = DiagnosticStatus.WARN
            status.message = (f"connected; {s['packets_dropped']} dropped, {s['crc_errors']} bad CRC, "
                              f"{s['header_errors']} bad headers so far")
        else:
            status.level, status.message = DiagnosticStatus.OK, "connected"
        keys = ["state", "frames_ok", "crc_errors", "header_errors", "dropped_frames", "packets_dropped",
                "queue_overflow_packets", "queue_depth", "packets_out", "connects", "disconnects",
                "connect_failures", "link_timeouts", "device_restarts", "clock_resyncs", "bytes_received",
                "bytes_discarded", "stream_gaps", "commands_unacked", "device_serial", "device_firmware",
                "device_state", "device_dropped"]
        status.values = [KeyValue(key=k, value=str(s[k])) for k in keys if k in s]
        status.values += [KeyValue(key=k, value=f"{v:.3f}") for k, v in rates.items()]
        status.values.append(KeyValue(key="published_packets", value=str(self.published_packets)))
        msg = DiagnosticArray()
        msg.header.stamp = ns_to_time_msg(now)
        msg.status = [status]
        self.pub_diag.publish(msg)

    def destroy_node(self):
        if not hasattr(self, "link"):       # constructor stopped early (bad parameter)
            return super().destroy_node()
        self._running = False
        if self.link._thread is not None:
            self.link.stop()
        self._publisher_thread.join(1.0)
        return super().destroy_node()


def main(args=None) -> int:
    return run_node(DriverNode, args)


if __name__ == "__main__":
    sys.exit(main())
