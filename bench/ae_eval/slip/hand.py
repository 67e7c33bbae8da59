# SPDX-License-Identifier: Apache-2.0
"""Interference across the fingertips of one hand: one source's bursts on every
fingertip, each fingertip's apex packets mapped to host time by its own link
(`link_clock`) and tested against the others' by `HandCoincidence`."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.dsp.coincidence import (
    COINCIDENCE_WAIT_S,
    COINCIDENCE_WINDOW_S,
    HandCoincidence,
)
from ae_tactile.sim.interference import burst_times_s
from ae_tactile.slip import SlipConfig
from ae_tactile.timesync import DeviceClockMapper

from .common import NS
from .interference import interference_finger, interference_outcome


def link_clock(rng, warmup_s: float = 12.0):
    """A fingertip's link on the simulator's model of a USB device, as `DeviceClockMapper`
    sees it: the device's sample clock runs at 1 + skew (|skew| <= 50 ppm, a crystal's
    tolerance) from an offset of its own; it sends a frame every 1 ms of its clock, which
    reaches the host after a latency floor of its own (50 .. 500 us: the host controller's
    polling and the driver's wake-up; two fingertips' mapped stamps of one burst differ by
    the difference of their floors) plus the wait for the next 1 ms poll (uniform) plus a
    tail (exponential, mean 200 us). Returns ``(to_host, arrival)``: to_host(t_ns) is the
    mapped host stamp (ns) of a device onset at true time t_ns (ns on the scene's clock =
    host time), from the link's mapper as it stands when the frame that carries it has
    come; arrival(t_ns) that frame's host arrival time (ns)."""
    skew = rng.uniform(-50e-6, 50e-6)
    d0 = rng.uniform(0.0, 10.0) * NS
    floor = rng.uniform(50e3, 500e3)
    frame = 1_000_000  # ns of device clock

    def device(t_ns):
        return (np.asarray(t_ns, np.float64) + d0) * (1.0 + skew)

    def true_of_device(d):
        return np.asarray(d, np.float64) / (1.0 + skew) - d0

    k0 = int(device(-warmup_s * NS) // frame) + 1
    mapper = DeviceClockMapper()
    state = {"k": k0}
    arrivals: dict[int, float] = {}

    def frame_arrival(k):
        if k not in arrivals:
            sent = float(true_of_device(k * frame))
            arrivals[k] = sent + floor + rng.uniform(0, 1e6) + rng.exponential(200e3)
        return arrivals[k]

    def advance(k_to):
        for k in range(state["k"], k_to + 1):
            mapper.update(k * frame, int(frame_arrival(k)))
        state["k"] = max(state["k"], k_to + 1)

    def carrier(t_ns):
        return int(float(device(t_ns)) // frame) + 1  # the first frame sent after the onset

    def to_host(t_ns):
        k = carrier(t_ns)
        advance(k)
        return mapper.to_host_ns(int(round(float(device(t_ns)))))

    def arrival(t_ns):
        return frame_arrival(carrier(t_ns))

    return to_host, arrival


def hand_interference_trial(
    seed: int,
    config: SlipConfig | None = None,
    *,
    n_fingers: int | None = None,
    duration_s: float = 1.0,
    window_s: float | None = None,
    wait_s: float | None = None,
    touch_rate_hz: float = 5.0,
) -> list[dict]:
    """Interference across the fingertips of one hand: one source's bursts (1 Hz .. 10 kHz,
    70 % periodic) enter the amplifier's input of every fingertip (2 .. 5, no wall echoes:
    one packet cannot tell them from an apex touch), each fingertip holding a touch of its
    own, through `interference_finger` (the packet tests and the timing, as the driver)
    and then `HandCoincidence`: every fingertip's apex packets, mapped to host time by its
    own link (`link_clock`), reach the others a transport delay (0.2 .. 1 ms) after their
    frame; an apex packet its own tests kept waits ``wait_s`` for them. Apex touches at
    random times (Poisson, ``touch_rate_hz`` on each fingertip, not rendered: their packet
    tests are measured per packet) go through the same test: the coincidence's cost to
    touches. Returns one row per fingertip: `interference_trial`'s counts after the
    coincidence, plus ``n_rejected_coincidence``, ``n_apex_touches``,
    ``n_apex_touches_kept``, ``reports_late`` and ``stamp_error_us`` (each burst's mapped
    stamp less its true time, this fingertip's bursts); ``alone_*``: the same fingertip
    without the hand (the control: phantom events, contacts, alarm onsets)."""
    rng = np.random.default_rng([7031, int(seed)])
    n_f = int(n_fingers) if n_fingers else int(rng.integers(2, 6))
    rate = float(math.exp(rng.uniform(math.log(1.0), math.log(1e4))))
    periodic = bool(rng.uniform() < 0.7)
    hand = {
        "medium": "silicone" if rng.uniform() < 0.5 else "water_skin",
        "sample_rate_hz": float(rng.choice([2e6, 5e6, 10e6])),
        "rate_hz": rate,
        "periodic": periodic,
        "burst_times_ns": np.round(
            burst_times_s(duration_s, rate, periodic=periodic, rng=rng) * NS
        ).astype(np.int64),
    }
    window_s = COINCIDENCE_WINDOW_S if window_s is None else window_s
    wait_s = COINCIDENCE_WAIT_S if wait_s is None else wait_s
    fingers = [_hand_finger(rng, seed, f, duration_s, hand, touch_rate_hz) for f in range(n_f)]
    rows = []
    for f, (st, apex, mapped, _, n_touch) in enumerate(fingers):
        hc = HandCoincidence(window_s=window_s, wait_s=wait_s)
        events = _coincidence_events(rng, f, fingers, hc)
        coincident, touches_kept = _hand_decisions(hc, events)
        alone = interference_outcome(st, config)
        out = interference_outcome(st, config, coincident)
        out.update(
            {
                "n_fingers": n_f,
                "finger": f,
                "window_s": hc.window_ns * 1e-9,
                "alone_phantom_events": alone["n_phantom_events"],
                "alone_contacts_created": alone["contacts_created"],
                "alone_alarm_onsets": alone["n_alarm_onsets"],
                "n_rejected_coincidence": sum(1 for k in coincident if not k[0]),
                "n_acoustic_rejected_coincidence": sum(1 for k in coincident if k[0]),
                "n_apex_touches": n_touch,
                "n_apex_touches_kept": touches_kept,
                "apex_touch_kept_expected": _touch_kept_expected(f, fingers, hc, duration_s),
                "hand_seed": int(seed),
                "reports_late": int(hc.counts["reports_late"]),
                "offsets_learnt": int(hc.counts["offsets_learnt"]),
                "stamp_error_us": [
                    round((m - a[0]) * 1e-3, 2) for a, m in zip(apex, mapped) if a[1] is False
                ],
            }
        )
        rows.append(out)
    return rows


def _hand_finger(rng, seed, f, duration_s, hand, touch_rate_hz):
    """Fingertip ``f`` of the hand: (its `interference_finger` state, its apex packets and
    random apex touches [(onset ns, acoustic? (None: a touch), ref, rejected)] in time
    order, their mapped host stamps, their frames' host arrival times [ns], the number of
    touches)."""
    st = interference_finger(
        1_000_000 + 8 * int(seed) + f,
        discriminate=True,
        duration_s=duration_s,
        input_without_echoes=True,
        hand=hand,
    )
    to_host, arrival = link_clock(rng)
    n_touch = int(rng.poisson(touch_rate_hz * duration_s))
    touch_ns = np.sort(rng.uniform(0.0, duration_s * NS, n_touch)).astype(np.int64)
    apex = list(st["apex"]) + [(int(t), None, i, False) for i, t in enumerate(touch_ns)]
    apex.sort(key=lambda a: a[0])
    mapped = [to_host(a[0]) for a in apex]
    came = [arrival(a[0]) for a in apex]
    return st, apex, mapped, came, n_touch


def _coincidence_events(rng, f, fingers, hc):
    """Fingertip ``f``'s (host time ns, order, kind, payload) events: the others' reports
    (a transport delay of 0.2 .. 1 ms after their frame), its own apex packets, the holds
    of those its own tests kept and their decisions."""
    _, apex, mapped, came, _ = fingers[f]
    events = []
    for g, (_, _, o_mapped, o_came, _) in enumerate(fingers):
        if g == f:
            continue
        for m, c in zip(o_mapped, o_came):
            events.append((c + rng.uniform(0.2e6, 1e6), 1, "report", (m, g)))
    for a, m, c in zip(apex, mapped, came):
        events.append((c, 2, "own", m))
        if a[3]:
            continue  # rejected by this fingertip's own tests
        events.append((c, 3, "hold", (m, a)))
        # decided when its wait is over, or when its frame comes if that is later
        events.append((m + hc.wait_ns, 0, "due", None) if c < m + hc.wait_ns
                      else (c, 4, "due", None))
    return events


def _touch_kept_expected(f, fingers, hc, duration_s):
    """The share of apex touches at random times fingertip ``f`` should keep: kept when no
    report lies within the window, the share of the trial the reports' windows leave free
    (their union's complement), each fingertip's reports less the offset learnt for it."""
    rep = np.sort(np.asarray(
        [m - hc.offsets_ns.get(str(g), 0)
         for g, fg in enumerate(fingers) if g != f for m in fg[2]], np.float64
    ))
    covered = (
        2 * hc.window_ns + np.minimum(np.diff(rep), 2 * hc.window_ns).sum() if rep.size else 0
    )
    return max(0.0, 1.0 - covered / (duration_s * NS))


def _hand_decisions(hc, events) -> tuple[set, int]:
    """Play a fingertip's (host time ns, order, kind, payload) events through its
    `HandCoincidence` in time order: (the refs it rejected, the apex touches it kept)."""
    coincident: set = set()
    touches_kept = 0
    for t, _, kind, payload in sorted(events, key=lambda e: (e[0], e[1])):
        if kind == "report":
            hc.add_others([payload[0]], payload[1])
        elif kind == "own":
            hc.add_own([payload])
        elif kind == "hold":
            hc.hold(payload[0], payload[1])
        else:
            kept, rejected = hc.due(int(t))
            touches_kept += sum(1 for a in kept if a[1] is None)
            coincident.update(_apex_key(a) for a in rejected if a[1] is not None)
    return coincident, touches_kept


def _apex_key(a) -> tuple:
    """The ref `interference_outcome` knows an apex packet (onset, acoustic?, ref, ...) by."""
    return (a[1], id(a[2]) if a[1] else a[2])
