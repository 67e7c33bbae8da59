# SPDX-License-Identifier: Apache-2.0
"""The `driver` node's parameters (`DRIVER_PARAMS`) and what is built from them: the body,
the link's configuration, the stream detector's options, the topics' QoS."""

from __future__ import annotations

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from ae_tactile.dsp.coincidence import COINCIDENCE_WAIT_S, COINCIDENCE_WINDOW_S
from ae_tactile.geometry import MEDIA, FingertipGeometry
from ae_tactile.link import MODES, LinkConfig
from ae_tactile.ros.node_utils import cpu_list_problem, hand_topic_problem
from ae_tactile.ros.params import Param, ParameterError, tunable

DRIVER_PARAMS = [
    Param(
        "port",
        "/dev/ttyACM0",
        "Serial device path or pyserial URL (socket://host:port, loop://, a pty path)",
        check=lambda v: None if isinstance(v, str) and v.strip() else "must be a non-empty string",
    ),
    Param(
        "baudrate",
        3_000_000,
        "Serial baud rate (bit/s); ignored by USB CDC, ptys and sockets",
        50,
        100_000_000,
    ),
    Param(
        "frame_id",
        "ae_tactile_fingertip",
        "TF frame of the fingertip (origin at the sphere centre, +z to the apex)",
        check=lambda v: (
            None if isinstance(v, str) and v.strip() else "must be a non-empty frame name"
        ),
    ),
    Param(
        "mode",
        "triggered",
        "Acquisition mode: 'triggered' (device cuts packets) or 'stream' (host cuts packets)",
        choices=MODES,
    ),
    Param(
        "sample_rate_hz",
        0,
        "ADC sample rate to set on the device (Hz); 0 keeps the device's",
        0,
        20_000_000,
    ),
    Param(
        "threshold_counts",
        0,
        "Device trigger threshold (ADC counts); 0 keeps the device's",
        0,
        32767,
    ),
    Param(
        "packet_samples",
        0,
        "Samples per channel of a triggered packet; 0 keeps the device's",
        0,
        8192,
    ),
    Param(
        "pre_trigger_samples",
        0,
        "Samples before the trigger in a packet; 0 = packet_samples/4",
        0,
        8191,
    ),
    Param(
        "reliable_qos",
        False,
        "Publish packets reliably (for recording) instead of sensor-data QoS",
    ),
    Param(
        "queue_max_batches",
        256,
        "Bound of the reader-to-publisher queue (overflow is counted as drops)",
        1,
        100_000,
    ),
    Param(
        "link_timeout_s",
        3.0,
        "Time without a valid frame after which the link counts as lost and "
        "reconnects (s); the device beats >= 1 Hz",
        0.1,
        60.0,
    ),
    Param("reconnect_max_s", 5.0, "Longest wait between reconnection attempts (s)", 0.1, 300.0),
    Param(
        "acquisition_timeout_s",
        2.5,
        "Time without a packet (or a STATUS saying it acquires) while acquisition is "
        "expected after which the link restarts it (STOP/START), then reconnects if "
        "another such time passes; more than the 1 s heartbeat period (0: never)",
        0.0,
        600.0,
        check=lambda v: None if v == 0 or v > 1.0 else "must be 0 (never) or > 1 s",
    ),
    Param(
        "clock_step_s",
        0.25,
        "Latency above the device-clock mapping that, clock_step_frames frames in a row, "
        "counts as a clock step (the mapping is rebuilt, stamps stay monotonic); above "
        "any host stall the link should ride out",
        0.001,
        3600.0,
    ),
    Param(
        "clock_step_frames",
        4,
        "Frames in a row above clock_step_s that make a clock step",
        1,
        1000,
    ),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics messages (s)", 0.05, 60.0),
    Param(
        "wait_for_subscribers",
        0,
        "Start acquisition only once this many subscribers are matched on 'contacts' "
        "or on 'packets' (a recorder; 'packets' only with pipeline:=false), so nothing is "
        "published before its consumers listen (0: at once)",
        0,
        100,
    ),
    Param(
        "cpu_affinity",
        "",
        "CPUs the driver process runs on, written as for taskset -c ('3', '2-3', '0,2'; "
        "empty: as started), its threads and its overlap worker included: a core of its "
        "own keeps the tail of the reflex path's latency short",
        check=cpu_list_problem,
        numbers_as_text=True,
    ),
    Param(
        "pipeline",
        True,
        "Localize and detect slip inside the driver (lowest latency); false: "
        "publish raw packets only, for the separate localizer and slip_detector nodes",
    ),
    Param(
        "hand_coincidence_topic",
        "",
        "Topic shared by the drivers of one hand's fingertips (absolute, e.g. "
        "/hand/apex_packets): each publishes the onsets of its apex packets there and "
        "drops an apex packet another fingertip saw at the same time (electrical "
        "interference reaches them all at once); empty: off",
        check=hand_topic_problem,
    ),
    tunable(
        Param(
            "hand_coincidence_window_s",
            COINCIDENCE_WINDOW_S,
            "Two fingertips' apex packets within this of each other (host clock) are one "
            "electrical event",
            1e-6,
            0.01,
        )
    ),
    tunable(
        Param(
            "hand_coincidence_wait_s",
            COINCIDENCE_WAIT_S,
            "How long an apex packet that one packet's tests cannot tell from interference "
            "waits for the other fingertips' reports (its contact event comes that much "
            "later); at least hand_coincidence_window_s",
            1e-4,
            1.0,
        )
    ),
    Param(
        "calibration_dir",
        "",
        "Where what the pipeline learns about each device (its pulse, its interference "
        "model, its echo) is kept, one file per serial number and body (radius, element "
        "offset, sound speed); empty: $ROS_HOME/ae_tactile/calibration (~/.ros/...); "
        "'none': not kept",
    ),
    Param(
        "calibration_reset",
        False,
        "Start the device's calibration from scratch (its file is replaced by the next save)",
    ),
    Param(
        "calibration_save_period_s",
        60.0,
        "How often the device's calibration is saved while running (and at shutdown) (s)",
        1.0,
        86_400.0,
    ),
    tunable(Param("markers", True, "Publish RViz markers on 'markers' (only while subscribed)")),
    Param("marker_period_s", 0.1, "Marker refresh period", 0.02, 5.0),
    Param("marker_lifetime_s", 2.0, "How long an event marker stays (fading)", 0.1, 60.0),
    Param(
        "slip_tick_period_s",
        0.02,
        "Period of the slip detector's time-keeping tick (quiet contacts fall back to STICK)",
        0.001,
        1.0,
    ),
    Param(
        "slip_lag_s",
        0.02,
        "The tick never moves the slip detector's clock past now minus this, "
        "so emissions still in flight are not overtaken",
        0.0,
        1.0,
    ),
    Param(
        "detector_threshold_sigma",
        6.0,
        "Stream mode: trigger threshold in noise sigmas",
        2.0,
        100.0,
    ),
    Param(
        "medium",
        "water_skin",
        "Fingertip body for SensorInfo: 'water_skin', 'silicone' or a label",
    ),
    Param("radius_m", 10e-3, "Sphere radius R (m)", 1e-3, 0.1),
    Param(
        "element_offset_m",
        1.5e-3,
        "PVDF element centre offset a (m): centres at (+-a, +-a, 0)",
        1e-4,
        0.02,
    ),
    Param("sound_speed_m_s", 0.0, "Sound speed c (m/s); 0 = the medium preset's", 0.0, 10_000.0),
    Param(
        "channel_gains",
        [1.0, 1.0, 1.0, 1.0],
        "Relative gain of channels 0..3 (calibration)",
        check=lambda v: (
            None if len(v) == 4 and all(g > 0 for g in v) else "needs 4 positive gains"
        ),
    ),
    Param(
        "highpass_hz", 100e3, "Analog front-end high-pass corner (Hz), for SensorInfo", 0.0, 5e6
    ),
]


#: Event topics: reliable, so a hand's controller never misses a touch or a slip.
EVENT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
#: `emissions`: reliable, depth 1000 (a second of emissions at the rate a slide gives)
EMISSION_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def geometry_from_params(p: dict) -> FingertipGeometry:
    """Fingertip geometry of the driver parameters (c = 0: the medium preset's)."""
    c = p["sound_speed_m_s"] or MEDIA.get(p["medium"], MEDIA["water_skin"])["sound_speed_m_s"]
    return FingertipGeometry(p["radius_m"], p["element_offset_m"], c)


def packet_qos(reliable: bool) -> QoSProfile:
    """Sensor-data QoS (best effort, depth 5) or reliable depth 100 for recording."""
    if reliable:
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=100,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
    return qos_profile_sensor_data


def detector_options(p: dict) -> dict:
    """Stream-mode detector settings: threshold, and the geometry's wall-echo delay 2R/c
    and largest arrival spread over the elements 2 sqrt(2) a / c."""
    c = p["sound_speed_m_s"] or MEDIA.get(p["medium"], MEDIA["water_skin"])["sound_speed_m_s"]
    return {
        "threshold_sigma": p["detector_threshold_sigma"],
        "echo_delay_s": 2.0 * p["radius_m"] / c,
        "channel_spread_s": max(3e-6, 2.0 * 2**0.5 * p["element_offset_m"] / c),
    }


def link_config_from_params(p: dict) -> LinkConfig:
    """LinkConfig from validated parameter values (0 = keep the device's setting)."""
    none0 = lambda v: None if v == 0 else int(v)  # noqa: E731
    packet_samples = none0(p["packet_samples"])
    if p["pre_trigger_samples"] and not packet_samples:
        raise ParameterError(
            "parameter 'pre_trigger_samples' needs 'packet_samples' (the device "
            "takes both together); set packet_samples too"
        )
    pre = p["pre_trigger_samples"] if packet_samples else None
    if packet_samples and pre >= packet_samples:
        raise ParameterError(
            f"parameter 'pre_trigger_samples' = {pre} must be < packet_samples = {packet_samples}"
        )
    try:
        return LinkConfig(
            port=p["port"].strip(),
            baudrate=p["baudrate"],
            mode=p["mode"],
            sample_rate_hz=none0(p["sample_rate_hz"]),
            threshold_counts=none0(p["threshold_counts"]),
            packet_samples=packet_samples,
            pre_trigger_samples=pre or None,
            queue_max_batches=p["queue_max_batches"],
            link_timeout_s=p["link_timeout_s"],
            acquisition_timeout_s=p["acquisition_timeout_s"],
            clock_step_s=p["clock_step_s"],
            clock_step_frames=p["clock_step_frames"],
            reconnect_max_s=max(p["reconnect_max_s"], 0.2),
            detector=detector_options(p),
        )
    except ValueError as exc:
        raise ParameterError(str(exc)) from exc
