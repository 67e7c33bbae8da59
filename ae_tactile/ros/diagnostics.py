# SPDX-License-Identifier: Apache-2.0
"""Diagnostics of the driver and the replay nodes: the link's status (frames, errors, rates)
and the pipeline's stages (localization counts by reason, the slip detector's state)."""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

#: link counters that make the status WARN when non-zero
LINK_PROBLEMS = (
    "crc_errors",
    "packets_dropped",
    "header_errors",
    "duplicate_frames",
    "truncated_frames",
    "sink_errors",
    "internal_errors",
    "frames_unusable",
    "packets_rejected_nonfinite",
    "packets_rejected_sample_rate",
    "port_busy",
    "acquisition_restarts",
    "acquisition_reconnects",
    "clock_steps",
    "behind",  # the reader is behind the device now (ae_tactile.link.lag)
    "behind_episodes",
)


def _busy(last_error: str) -> bool:
    """The last open failed because another link owns the port (`PortBusy`, or pyserial's
    exclusive lock)."""
    return "in use by" in last_error or "exclusive" in last_error.lower()


def link_rates(stats: dict, last, now_ns: int) -> dict:
    """Frame and packet rates [Hz] since ``last`` ((ns, stats) of the previous call, or None)."""
    if last is None:
        return {}
    t0, s0 = last
    dt = max((now_ns - t0) * 1e-9, 1e-9)
    return {
        "frame_rate_hz": (stats.get("frames_ok", 0) - s0.get("frames_ok", 0)) / dt,
        "packet_rate_hz": (stats.get("packets_out", 0) - s0.get("packets_out", 0)) / dt,
    }


def link_status(
    node_name: str, hardware_id: str, s: dict, rates: dict, published_packets: int
) -> DiagnosticStatus:
    """DiagnosticStatus of the fingertip link.

    Parameters
    ----------
    node_name, hardware_id : str
        The node's fully qualified name and the device's serial number (or port).
    s : dict
        `FingertipLink.stats()`.
    rates : dict
        `link_rates`.
    published_packets : int
        Raw packets published.

    Returns
    -------
    DiagnosticStatus
        ERROR unless connected (``port busy: ...`` naming the port and its owner when
        another driver holds it), WARN with problems counted (the link's restarts of an
        idle device, its clock steps included), else OK.
    """
    link = DiagnosticStatus()
    link.name = f"{node_name}: fingertip link"
    link.hardware_id = hardware_id
    problems = {k: s.get(k, 0) for k in LINK_PROBLEMS if s.get(k, 0)}
    if s["state"] != "connected":
        why = s["last_error"]
        link.level = DiagnosticStatus.ERROR
        link.message = f"port busy: {why}" if _busy(why) else f"link {s['state']}: {why}"
    elif problems:
        link.level = DiagnosticStatus.WARN
        link.message = "connected; " + ", ".join(
            f"{v} {k.replace('_', ' ')}" for k, v in problems.items()
        )
    else:
        link.level, link.message = DiagnosticStatus.OK, "connected"
    link.values = [KeyValue(key=k, value=str(v)) for k, v in sorted(s.items())]
    link.values += [KeyValue(key=k, value=f"{v:.3f}") for k, v in rates.items()]
    link.values += [KeyValue(key="published_packets", value=str(published_packets))]
    return link


def pipeline_statuses(
    node_name: str,
    hardware_id: str,
    pipeline,
    slip_stage,
    events: int,
    slip_events: int,
    emissions: int | None = None,
    calibration: dict | None = None,
) -> list:
    """DiagnosticStatus of the localization (``pipeline``: a ContactPipeline, its counts by
    reason) and slip stages; ``pipeline`` None: the slip stage's only."""
    out = []
    if pipeline is not None:
        out.append(_localization_status(node_name, hardware_id, pipeline, events, calibration))
    if slip_stage is not None:
        slip = DiagnosticStatus()
        slip.name = f"{node_name}: slip detection"
        slip.hardware_id = hardware_id
        counts = slip_stage.all_counts()
        st = slip_stage.state
        slip.level = DiagnosticStatus.OK
        dropped = sum(v for k, v in counts.items() if "rejected" in k)
        slip.message = f"{st.state.name}, {slip_events} slip events, {dropped} inputs rejected"
        if dropped:
            slip.level = DiagnosticStatus.WARN
        slip.values = [KeyValue(key=k, value=str(v)) for k, v in sorted(counts.items())]
        slip.values += [KeyValue(key="published_slip_events", value=str(slip_events))]
        if emissions is not None:
            slip.values += [KeyValue(key="published_emissions", value=str(emissions))]
            slip.values += [KeyValue(key="current_contacts",
                                     value=str(len(slip_stage.contacts)))]
        out.append(slip)
    return out


def _localization_status(node_name, hardware_id, pipeline, events,
                         calibration=None) -> DiagnosticStatus:
    loc = DiagnosticStatus()
    loc.name = f"{node_name}: localization"
    loc.hardware_id = hardware_id
    c = dict(pipeline.all_counts())
    c.setdefault("events", 0)
    c.setdefault("packets", 0)
    rejected = sum(v for k, v in c.items() if k.startswith("rejected_"))
    loc.level = DiagnosticStatus.OK
    loc.message = f"{c['events']} events from {c['packets']} packets, {rejected} rejected"
    if c["packets"] >= 20 and rejected > 0.5 * c["packets"]:
        loc.level = DiagnosticStatus.WARN
    loc.values = [KeyValue(key=k, value=str(v)) for k, v in sorted(c.items())]
    loc.values += [
        KeyValue(key="method", value=pipeline.localizer.method),
        KeyValue(key="published_events", value=str(events)),
        KeyValue(key="interference_echo_test", value=pipeline.localizer.echo_test_status()),
        KeyValue(key="interference_model", value=pipeline.localizer.interference_model_status()),
    ]
    loc.values += [KeyValue(key=k, value=str(v)) for k, v in (calibration or {}).items()]
    if calibration and calibration.get("calibration_last_error"):
        loc.level = max(loc.level, DiagnosticStatus.WARN)
        loc.message += f"; calibration: {calibration['calibration_last_error']}"
    return loc
