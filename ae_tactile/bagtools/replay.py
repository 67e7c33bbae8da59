# SPDX-License-Identifier: Apache-2.0
"""A bag's raw packets re-interpreted: localization (any estimator), then slip detection.

Every packet is checked on its own (sample rate > 0 and finite, 4 channels, sizes,
finite samples, onset in range): a bad one is rejected with its reason, never the
whole replay. The `sensor_info` recorded with the packets sets the geometry and the
channel gains, so the bag is self-describing.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import Localizer, Reason
from ae_tactile.records import EventType
from ae_tactile.slip import LocalizedEvent, SlipConfig, SlipDetector

from .reader import ReplayResult, read_bag, typestore
from .recovery import _count

TOUCH, DETOUCH = int(EventType.TOUCH), int(EventType.DETOUCH)


def _topic_ns(topic: str) -> str:
    return topic.rsplit("/", 1)[0] if "/" in topic.strip("/") else ""


def check_packet(p) -> tuple[str | None, np.ndarray | None, float]:
    """(reason or None, samples (4, N) float32, sample rate) of one recorded Packet."""
    try:
        n = int(p.samples_per_channel)
        x = np.asarray(p.samples, dtype=np.float32)
        fs = float(p.sample_rate_hz)
        onset = int(p.onset_index)
        if int(p.channel_count) != 4 or n < 1 or x.size != 4 * n:
            return "MALFORMED", None, 0.0
    except (TypeError, ValueError, OverflowError):
        return "MALFORMED", None, 0.0
    if not (math.isfinite(fs) and fs > 0):
        return "BAD_SAMPLE_RATE", None, 0.0
    if not 0 <= onset < n:
        return "BAD_ONSET_INDEX", None, 0.0
    if not np.isfinite(x).all():
        return "NON_FINITE_SAMPLES", None, 0.0
    return None, x.reshape(4, n), fs


def replay(
    path,
    *,
    method: str = "ml",
    packet_topic: str | None = None,
    slip_config=None,
    localize_options: dict | None = None,
) -> ReplayResult:
    """Re-localize every PacketArray of a bag and run the slip detector over the events.

    Damaged bags, foreign messages and bad packets are counted in the result (see
    `ReplayResult`), never raised.

    Parameters
    ----------
    path : str or os.PathLike
        A rosbag2 directory, or one .db3 / .mcap file.
    method : str
        Localization estimator (`ae_tactile.localization.available_methods`).
    packet_topic : str or None
        Only this topic's packets (None: every topic's).
    slip_config : SlipConfig or None
        The slip detector's settings (None: its defaults).
    localize_options : dict or None
        Keyword arguments of the `Localizer`.

    Returns
    -------
    ReplayResult
        Contact and slip events, and what was refused or lost.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    """
    if not Path(path).exists():
        raise FileNotFoundError(f"no such bag: {path}")
    store = typestore()
    loc = Localizer(method, **(localize_options or {}))
    det = SlipDetector(slip_config or SlipConfig(), contact_events=True)
    out = ReplayResult(geometry=FingertipGeometry())
    gains = None
    for topic, msgtype, _, msg in read_bag(path, store, packet_topic, out):
        if msgtype.endswith("SensorInfo"):
            gains = _sensor_info(msg, msgtype, out, gains)
        else:
            _replay_packets(loc, msg, msgtype, topic, gains, out)
    out.contacts.sort(key=lambda e: e["time_ns"])
    _detect_slip(det, out)
    return out


def _sensor_info(msg, msgtype: str, out: ReplayResult, gains):
    """A SensorInfo sets the geometry and returns the channel gains (None: not usable);
    one with values out of range is counted and ignored (the gains stay)."""
    try:
        geo = FingertipGeometry(msg.radius_m, msg.element_offset_m, msg.sound_speed_m_s)
    except Exception:  # noqa: BLE001 - values out of range
        _count(out.undecodable, f"{msgtype} (invalid values, ignored)")
        return gains
    out.geometry = geo
    g = np.asarray(msg.channel_gains, dtype=float)
    return g if g.shape == (4,) and np.all(g > 0) and np.all(np.isfinite(g)) else None


def _replay_packets(loc, msg, msgtype: str, topic: str, gains, out: ReplayResult) -> None:
    """The contact events of one PacketArray: packets checked, grouped by window length
    and sample rate, localized group by group."""
    try:
        frame = str(msg.header.frame_id)
        packets = list(msg.packets)
    except Exception:  # noqa: BLE001 - a foreign definition
        _count(out.undecodable, msgtype)
        return
    groups: dict = {}
    for p in packets:
        out.packets += 1
        reason, x, fs = check_packet(p)
        if reason is not None:
            _count(out.rejected, reason)
            continue
        groups.setdefault((x.shape[1], fs), []).append((p, x))
    for (_, fs), items in groups.items():
        for sub, res in _localize(loc, items, fs, out.geometry, gains, out):
            _contacts(out, sub, res, fs, frame, topic)


def _detect_slip(det: SlipDetector, out: ReplayResult) -> None:
    """The slip detector over the emissions, in time order: each emission's reading and
    contact, the contacts' begin / end and the slip events; then time lets the contacts
    whose release is confirmed end."""
    e = None
    for e in out.contacts:
        ev = LocalizedEvent(
            time_ns=e["time_ns"],
            point_m=e["point_m"],
            covariance_m2=e["covariance_m2"],
            polarity=1 if e["event_type"] == TOUCH else -1,
            amplitude_v=e["amplitude_v"],
            confidence=e["confidence"],
            packet_id=e["packet_id"],
        )
        try:
            slips = det.process(ev)
        except Exception:  # noqa: BLE001 - counted, replay goes on
            _count(out.rejected, "SLIP_DETECTOR_ERROR")
            e["reading"], e["contact_id"] = 0, 0
            continue
        reading, cid = det.last_reading
        e["reading"], e["contact_id"] = int(reading), max(int(cid), 0)
        _slip_events(out, slips, e)
    if e is not None and det.now_ns is not None:
        # the releases confirmed by the time after the last emission (the longest wait)
        wait_s = max(det.config.release_confirm_s, det.config.quiet_s)
        det.advance(det.now_ns + int(wait_s * 1e9) + 1)
        _slip_events(out, det.pop_events(), e)


def _slip_events(out: ReplayResult, slips, e: dict) -> None:
    """The detector's events as dicts: a contact's TOUCH / DETOUCH to ``contact_events``,
    the others to ``slip`` (frame and namespace of the emission ``e``)."""
    for s in slips:
        kind = int(s.kind)
        (out.contact_events if kind in (TOUCH, DETOUCH) else out.slip).append(
            {
                "time_ns": int(s.time_ns),
                "frame_id": e["frame_id"],
                "topic_ns": e["topic_ns"],
                "event_type": kind,
                "point_m": np.asarray(s.position_m, float),
                "covariance_m2": np.asarray(s.covariance_m2, float),
                "tau_x_s": math.nan,
                "tau_y_s": math.nan,
                "amplitude_v": math.nan,
                "confidence": float(s.confidence),
                "packet_ids": [int(i) for i in s.packet_ids],
                "emission_rate_hz": float(s.emission_rate_hz),
                "spatial_period_m": float(s.spatial_period_m),
                "slip_direction": np.asarray(s.slip_direction, float),
                "contact_id": max(int(s.contact_id), 0),
            }
        )


def _localize(loc, items, fs, geometry, gains, out):
    """Localize a group of packets; if the estimator raises, each packet on its own."""

    def run(group):
        onsets = np.array([int(p.onset_index) for p, _ in group])
        return loc(
            np.stack([x for _, x in group]),
            fs,
            onsets,
            geometry=geometry,
            channel_gains=gains,
            saturated=np.array([bool(p.saturated) for p, _ in group]),
        )

    try:
        return [(items, run(items))]
    except Exception:  # noqa: BLE001
        done = []
        for item in items:
            try:
                done.append(([item], run([item])))
            except Exception:  # noqa: BLE001
                _count(out.rejected, "LOCALIZER_ERROR")
        return done


def _contacts(out, items, res, fs, frame, topic):
    travel = out.geometry.arrival_times_s(np.nan_to_num(res.point_m)).min(axis=-1)
    for i, (p, _) in enumerate(items):
        if not res.accepted[i]:
            _count(out.rejected, Reason(int(res.reason[i])).name)
            continue
        if not (np.all(np.isfinite(res.point_m[i])) and np.isfinite(travel[i])):
            _count(out.rejected, "NON_FINITE_RESULT")
            continue
        stamp = int(p.stamp.sec) * 1_000_000_000 + int(p.stamp.nanosec)
        t_ns = stamp + int(round(int(p.onset_index) * 1e9 / fs - travel[i] * 1e9))
        out.contacts.append(
            {
                "time_ns": t_ns,
                "frame_id": frame,
                "topic_ns": _topic_ns(topic),
                "event_type": DETOUCH if res.polarity[i] < 0 else TOUCH,
                "polarity": -1 if res.polarity[i] < 0 else 1,
                "point_m": res.point_m[i].copy(),
                "covariance_m2": res.covariance_m2[i].copy(),
                "tau_x_s": float(res.tau_x_s[i]),
                "tau_y_s": float(res.tau_y_s[i]),
                "amplitude_v": float(res.amplitude_v[i]),
                "confidence": float(res.confidence[i]),
                "packet_id": int(p.sequence_id),
            }
        )
