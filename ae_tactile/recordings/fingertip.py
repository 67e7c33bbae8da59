# SPDX-License-Identifier: Apache-2.0
"""A 4-channel fingertip recording replayed through the live device's pipeline.

The hits of the four channels within the geometry's largest inter-element delay (plus the
AIC's spread) form one emission; around its earliest onset a window is cut as the device
cuts its packets (``pretrigger_s`` before, ``window_s`` long), and the windows go, in time
order and in batches as a read cycle would give them, through `ContactPipeline`
(`PacketLocalizer` and `SlipStage`, the driver's own code), giving contact events (TOUCH /
DETOUCH, stamped at the emission time on the file's clock) and slip events.

Channel order is that of docs/conventions.md (k = 0..3 <-> (xi, eta) = (+1,+1), (+1,-1),
(-1,+1), (-1,-1)); ``channel_map[k]`` names the file row that holds fingertip channel k.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.pipeline import ContactPipeline, PacketLocalizer, PacketView, SlipStage
from ae_tactile.slip import SlipConfig

from .hits import Hit
from .locate import group_hits
from .readers import Recording, RecordingError

#: the device's packet window: pre-trigger and length [s] (the simulator's triggered
#: source and the virtual device use the same)
PRETRIGGER_S = 8e-6
WINDOW_S = 40e-6
#: onset spread allowed on top of the geometry's largest delay [s] (AIC picks, noise)
GROUP_MARGIN_S = 2e-6
#: windows per pipeline call (a read cycle's batch)
BATCH = 4
#: longest wait for the overlap resolver at the end of a replay [s]
IDLE_TIMEOUT_S = 120.0


@dataclass
class FingertipReplay:
    """What the pipeline made of a fingertip recording.

    ``contacts`` and ``slip`` are `ae_tactile.records.ContactRecord` s (time_ns on the
    file's clock); ``windows`` the packets cut (`PacketView`); ``counts`` the pipeline's
    counts plus windows that could not be cut, by reason.
    """

    contacts: list = field(default_factory=list)
    slip: list = field(default_factory=list)
    windows: list = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)


def parse_channel_map(text: str | None) -> tuple[int, ...] | None:
    """``"2,0,3,1"`` -> (2, 0, 3, 1): the file row of fingertip channel k = 0..3."""
    if text is None or not str(text).strip():
        return None
    try:
        m = tuple(int(v) for v in str(text).split(","))
    except ValueError:
        raise ValueError(f"channel map must read 'r0,r1,r2,r3', got {text!r}") from None
    return check_channel_map(m)


def check_channel_map(channel_map) -> tuple[int, ...]:
    m = tuple(int(v) for v in channel_map)
    if len(m) != 4 or len(set(m)) != 4 or min(m) < 0:
        raise ValueError(f"channel map must name 4 different file rows, got {channel_map!r}")
    return m


def fingertip_windows(rec: Recording, hits: list[Hit], *, geometry: FingertipGeometry,
                      channel_map=None, pretrigger_s: float = PRETRIGGER_S,
                      window_s: float = WINDOW_S, counts: Counter | None = None,
                      first_id: int = 0) -> list[PacketView]:
    """One packet per emission of a 4-channel fingertip recording.

    Parameters
    ----------
    rec : Recording
        At least 4 channels.
    hits : list of Hit
        Its hits (`find_hits`).
    geometry : FingertipGeometry
    channel_map : sequence of 4 int or None
        File row of fingertip channel k (None: rows 0..3).
    pretrigger_s, window_s : float
        The packet window [s].
    counts : Counter or None
        Takes the emissions whose window does not fit in the recording.
    first_id : int
        Sequence id of the first packet.

    Returns
    -------
    list of PacketView
    """
    m = check_channel_map(channel_map or (0, 1, 2, 3))
    if max(m) >= rec.n_channels:
        raise RecordingError(f"{rec.source}: {rec.n_channels} channel(s); a fingertip replay "
                             f"needs the rows {m}")
    fs = rec.sample_rate_hz
    pre = int(round(pretrigger_s * fs))
    n = int(round(window_s * fs))
    rows = {rec.channels[r] for r in m}
    mine = [h for h in hits if h.channel in rows]
    # the arrivals at the four elements spread by at most 2 sqrt(2) a / c < 3 max_delay_s
    span = 3.0 * geometry.max_delay_s + GROUP_MARGIN_S
    x = rec.samples_v[list(m)]
    views = []
    for ev in group_hits(mine, span):
        onset = min(mine[i].onset_index for i in ev)
        start = onset - pre
        if start < 0 or start + n > rec.n_samples:
            if counts is not None:
                counts["window_outside_recording"] += 1
            continue
        stamp_ns = int(round((rec.start_time_s + start / fs) * 1e9))
        noise = float(np.sqrt(np.mean([mine[i].noise_rms_v ** 2 for i in ev])))
        views.append(PacketView(np.ascontiguousarray(x[:, start:start + n]), fs, pre,
                                stamp_ns, first_id + len(views), noise_rms_v=noise))
    return views


def replay_fingertip(recordings, hits_per_record, *, geometry: FingertipGeometry | None = None,
                     channel_map=None, method: str = "ml", slip_config: SlipConfig | None = None,
                     pretrigger_s: float = PRETRIGGER_S,
                     window_s: float = WINDOW_S) -> FingertipReplay:
    """Replay fingertip recordings through the live device's `ContactPipeline`.

    Parameters
    ----------
    recordings : list of Recording
        Each with the fingertip's 4 channels (``channel_map``).
    hits_per_record : list of list of Hit
        The hits of each recording.
    geometry : FingertipGeometry or None
        None: the default sensor (docs/conventions.md).
    channel_map : sequence of 4 int or None
        File row of fingertip channel k (None: rows 0..3).
    method : str
        Localization estimator.
    slip_config : SlipConfig or None
        The slip detector's settings (None: its defaults).
    pretrigger_s, window_s : float
        The packet window [s].

    Returns
    -------
    FingertipReplay
    """
    geo = geometry or FingertipGeometry()
    out = FingertipReplay()
    for rec, hits in zip(recordings, hits_per_record):
        out.windows += fingertip_windows(rec, hits, geometry=geo, channel_map=channel_map,
                                         pretrigger_s=pretrigger_s, window_s=window_s,
                                         counts=out.counts, first_id=len(out.windows))
    out.windows.sort(key=lambda w: w.stamp_ns)
    pipe = ContactPipeline(PacketLocalizer(method, geometry=geo),
                           SlipStage(slip_config or SlipConfig()))
    try:
        for i in range(0, len(out.windows), BATCH):
            pipe.process(out.windows[i:i + BATCH], out.contacts.extend, out.slip.extend)
        if not pipe.wait_idle(IDLE_TIMEOUT_S):
            out.counts["overlap_resolver_timeout"] += 1
        pipe.run_pending_slip()
    finally:
        pipe.close()
    out.counts.update(pipe.all_counts())
    out.contacts.sort(key=lambda c: c.time_ns)
    return out


def contact_row(c) -> dict:
    """A contact or slip event as a flat dict (CSV / JSON)."""
    x, y, z = (float(v) for v in c.point_m)
    return {"time_s": c.time_ns * 1e-9, "event_type": int(c.event_type),
            "x_m": x, "y_m": y, "z_m": z,
            "polar_deg": math.degrees(c.polar_rad) if c.polar_rad == c.polar_rad else math.nan,
            "azimuth_deg": math.degrees(c.azimuth_rad)
            if c.azimuth_rad == c.azimuth_rad else math.nan,
            "amplitude_v": float(c.amplitude_v), "confidence": float(c.confidence),
            "packet_ids": " ".join(str(i) for i in c.packet_ids)}
