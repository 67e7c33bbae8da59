# SPDX-License-Identifier: Apache-2.0
"""`monitor`: a readable live log of events, scored against the simulator's ground truth.

Subscribes to `emissions` (every localized emission with its reading), `contacts` (a
contact's begin and end), `slip` (slip events), `contact_state` and, when a simulated
fingertip runs, `sim/ground_truth`. Each emission and event is printed once its ground
truth had time to arrive (``print_delay_s``), with its position error and end-to-end
latency (receive time - emission stamp). `summary()` scores the run: emissions found /
missed / false, touch-release typing by polarity, RMS position error, latency; and, with
the scene's truth (`ae_tactile.scoring`), the contact state against the true one (share
of time right), false alarms, SLIP timing against each gross slip, the precursor's lead.
"""

from __future__ import annotations

import bisect
import math
import sys
import time
from dataclasses import dataclass

import numpy as np
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import Empty

from ae_tactile.evaluation import match_by_time, score
from ae_tactile.msg import ContactEvent, ContactState, Emission
from ae_tactile.records import EVENT_NAMES, READING_NAMES, STATE_NAMES
from ae_tactile.ros.conversions import time_msg_to_ns
from ae_tactile.ros.node_utils import LATCHED
from ae_tactile.ros.sim_fingertip_node import TRUTH_QOS
from ae_tactile.scoring import score_run

TRUTH_KIND = {
    ContactEvent.TOUCH: "touch",
    ContactEvent.DETOUCH: "release",
    ContactEvent.SLIP_PRECURSOR: "micro_slip",
    ContactEvent.SLIP: "slip",
    ContactEvent.TEXTURE: "texture",
}


@dataclass
class Seen:
    stamp_ns: int
    received_ns: int
    msg: ContactEvent


class MonitorNode(Node):
    def __init__(
        self, print_live: bool = True, print_delay_s: float = 0.05, out=sys.stdout, **kwargs
    ):
        super().__init__("monitor", **kwargs)
        self.print_live = print_live
        self.print_delay_ns = int(print_delay_s * 1e9)
        self.out = out
        self.truth: list[ContactEvent] = []
        self.truth_ns: list[int] = []
        self.contacts: list[Seen] = []  # a contact's TOUCH (begin) / DETOUCH (end)
        self.slip: list[Seen] = []
        self.emissions: list[Seen] = []
        #: (stamp ns, state, state_since ns, current contacts) of each ContactState
        self.states: list[tuple[int, int, int, int]] = []
        self._queue: list[tuple[str, Seen]] = []
        self.t0_ns: int | None = None
        self.create_subscription(ContactEvent, "sim/ground_truth", self._on_truth, TRUTH_QOS)
        self.create_subscription(
            ContactEvent, "contacts", lambda m: self._on(m, self.contacts, "contact"), 1000
        )
        self.create_subscription(
            ContactEvent, "slip", lambda m: self._on(m, self.slip, "slip"), 1000
        )
        self.create_subscription(
            Emission, "emissions", lambda m: self._on(m, self.emissions, "emission"), 1000
        )
        self.create_subscription(ContactState, "contact_state", self._on_state, LATCHED)
        self.create_timer(0.02, self._flush)

    def _on_truth(self, msg: ContactEvent) -> None:
        t = time_msg_to_ns(msg.header.stamp)
        i = bisect.bisect_right(self.truth_ns, t)
        self.truth_ns.insert(i, t)
        self.truth.insert(i, msg)

    def _now(self) -> int:
        return self.get_clock().now().nanoseconds

    def _on(self, msg, store: list, kind: str) -> None:
        seen = Seen(time_msg_to_ns(msg.header.stamp), self._now(), msg)
        store.append(seen)
        if self.t0_ns is None:
            self.t0_ns = seen.stamp_ns
        self._queue.append((kind, seen))

    def _on_state(self, msg: ContactState) -> None:
        changed = not self.states or self.states[-1][1] != msg.state
        stamp, since = time_msg_to_ns(msg.header.stamp), time_msg_to_ns(msg.state_since)
        # a state that began before anything happened (since 0): from its message on
        self.states.append((stamp, msg.state, since if since > 0 else stamp, len(msg.contacts)))
        if self.print_live and changed:
            t = (
                time_msg_to_ns(msg.header.stamp) - (self.t0_ns or time_msg_to_ns(msg.header.stamp))
            ) * 1e-9
            ids = ", ".join(str(c.id) for c in msg.contacts)
            print(
                f"{t:9.4f} s  state -> {STATE_NAMES.get(msg.state, msg.state)}"
                f"  (contacts: {ids or 'none'})",
                file=self.out,
                flush=True,
            )

    def _nearest_truth(self, stamp_ns: int, point, tolerance_ns: int = 1_000_000):
        """The ground-truth emission within tolerance_ns of stamp_ns nearest to ``point``
        (dense emissions can be closer in time than the stamps' accuracy)."""
        lo = bisect.bisect_left(self.truth_ns, stamp_ns - tolerance_ns)
        hi = bisect.bisect_right(self.truth_ns, stamp_ns + tolerance_ns)
        if lo >= hi:
            return None
        return min(
            self.truth[lo:hi],
            key=lambda t: math.dist(point, (t.position.x, t.position.y, t.position.z)),
        )

    def _flush(self) -> None:
        now = self._now()
        ready = [q for q in self._queue if now - q[1].received_ns >= self.print_delay_ns]
        self._queue = [q for q in self._queue if now - q[1].received_ns < self.print_delay_ns]
        if not self.print_live:
            return
        for kind, s in ready:
            m = s.msg
            t = (s.stamp_ns - self.t0_ns) * 1e-9
            p = m.position
            name = (f"~{READING_NAMES.get(m.reading, m.reading).lower()}" if kind == "emission"
                    else EVENT_NAMES.get(m.event_type, m.event_type))
            line = (
                f"{t:9.4f} s  {name:<14s} "
                f"at ({p.x * 1e3:+6.2f}, {p.y * 1e3:+6.2f}, {p.z * 1e3:+6.2f}) mm"
            )
            if kind != "emission":
                line += f"  contact {m.contact_id}"
            if kind == "emission":
                truth = self._nearest_truth(s.stamp_ns, (p.x, p.y, p.z))
                if truth is not None:
                    err = math.dist(
                        (p.x, p.y, p.z), (truth.position.x, truth.position.y, truth.position.z)
                    )
                    kind = TRUTH_KIND.get(truth.event_type, "?")
                    line += f"  err {err * 1e6:6.1f} um  [truth: {kind}]"
                line += f"  conf {m.confidence:.2f}"
            elif kind == "slip":
                if not math.isnan(m.emission_rate_hz):
                    line += f"  rate {m.emission_rate_hz:6.1f} Hz"
                if not math.isnan(m.spatial_period_m):
                    line += f"  period {m.spatial_period_m * 1e3:.3f} mm"
                if not math.isnan(m.slip_direction.x):
                    d = m.slip_direction
                    line += f"  dir ({d.x:+.2f}, {d.y:+.2f}, {d.z:+.2f})"
            line += f"  latency {(s.received_ns - s.stamp_ns) * 1e-6:5.2f} ms"
            print(line, file=self.out, flush=True)

    # ------------------------------------------------------------------ picture
    def report_data(self, truth_score: dict | None = None) -> dict:
        """The run as plain rows for `ae_tactile.report.write_run_summary`: events (time from
        the first event, type, point, latency: a contact's begin / end and the slip events),
        the emissions (time, point, reading name), the ground truth, the contact-state
        changes and, with the scene's truth (``truth_score``: `summary`'s "truth"), the true
        state's."""
        t0 = self.t0_ns or 0
        events = [
            {
                "time_s": (x.stamp_ns - t0) * 1e-9,
                "type": int(x.msg.event_type),
                "x_m": x.msg.position.x,
                "y_m": x.msg.position.y,
                "z_m": x.msg.position.z,
                "latency_s": (x.received_ns - x.stamp_ns) * 1e-9,
            }
            for x in sorted(self.contacts + self.slip, key=lambda x: x.stamp_ns)
        ]
        truth = [
            {
                "x_m": t.position.x,
                "y_m": t.position.y,
                "z_m": t.position.z,
                "time_s": (time_msg_to_ns(t.header.stamp) - t0) * 1e-9,
            }
            for t in self.truth
            if t.confidence > 0
        ]
        states = [
            {"time_s": (since - t0) * 1e-9, "state": STATE_NAMES.get(st, str(st))}
            for _, st, since, _ in self.states
        ]
        emissions = [
            {"time_s": (x.stamp_ns - t0) * 1e-9, "x_m": x.msg.position.x,
             "y_m": x.msg.position.y, "reading": READING_NAMES.get(x.msg.reading, "UNKNOWN")}
            for x in self.emissions
        ]
        out = {"events": events, "truth": truth, "contact_state": states,
               "emissions": emissions}
        if truth_score:
            shift = (truth_score["t0_ns"] - t0) * 1e-9
            out["truth_state"] = [{"time_s": t + shift, "state": st}
                                  for t, st in truth_score["truth_timeline"]]
        return out

    # ------------------------------------------------------------------ summary
    def summary(self, gross_slip_times_ns=(), slip_windows_ns=(), scene_truth=None,
                end_ns: int | None = None) -> dict:
        """Scores of the run so far (see the module docstring). ``slip_windows_ns``: per
        gross slip, the start of the part of the scene it belongs to (precursors count from
        there); default: anything before the gross slip. ``scene_truth``: the scene's truth
        (sim/scene_truth's "truth"), for "truth" (`ae_tactile.scoring.score_run`; the
        ground truth alone without it); ``end_ns``: the scene's end (ROS ns)."""
        captured = [t for t in self.truth if t.confidence > 0]
        tr_ns = [time_msg_to_ns(t.header.stamp) for t in captured]
        tr_pt = [(t.position.x, t.position.y, t.position.z) for t in captured]
        tr_pol = [t.amplitude_v for t in captured]
        ev_ns = [s.stamp_ns for s in self.emissions]
        ev_pt = [(s.msg.position.x, s.msg.position.y, s.msg.position.z) for s in self.emissions]
        ev_pol = [1 if s.msg.polarity >= 0 else -1 for s in self.emissions]
        sc = score(tr_ns, tr_pt, tr_pol, ev_ns, ev_pt, ev_pol)
        out = {
            "emissions": sc.as_dict(),
            "truth_total": len(self.truth),
            "truth_not_captured_by_device": len(self.truth) - len(captured),
        }
        # touch / release only
        tr_idx = [
            i
            for i, t in enumerate(captured)
            if t.event_type in (ContactEvent.TOUCH, ContactEvent.DETOUCH)
        ]
        pairs = dict(match_by_time(tr_ns, ev_ns, 1_000_000, tr_pt, ev_pt))
        found = [i for i in tr_idx if i in pairs]
        typed = [
            i
            for i in found
            if (captured[i].event_type == ContactEvent.TOUCH) == (ev_pol[pairs[i]] > 0)
        ]
        out["touch_release"] = {
            "truth": len(tr_idx),
            "found": len(found),
            "typed_correctly": len(typed),
        }
        # a DETOUCH is decided once the release is confirmed (a quiet time after it): its
        # delay is not the path's latency, and is shown on its own
        reflex = [s for s in self.contacts if s.msg.event_type == ContactEvent.TOUCH]
        detouch = [s for s in self.contacts if s.msg.event_type == ContactEvent.DETOUCH]
        out["latency_ms"] = _latency(reflex + self.slip + self.emissions)
        out["latency_by_kind_ms"] = {
            "TOUCH": _latency(reflex), "slip": _latency(self.slip),
            "emissions": _latency(self.emissions), "DETOUCH": _latency(detouch),
        }
        counts = {}
        for s in self.slip:
            name = EVENT_NAMES.get(s.msg.event_type, str(s.msg.event_type))
            counts[name] = counts.get(name, 0) + 1
        out["slip_events"] = counts
        leads = []
        starts = list(slip_windows_ns) + [0] * (len(gross_slip_times_ns) - len(slip_windows_ns))
        for g, start in zip(gross_slip_times_ns, starts):
            pre = [
                s.stamp_ns
                for s in self.slip
                if s.msg.event_type == ContactEvent.SLIP_PRECURSOR and start <= s.stamp_ns < g
            ]
            leads.append((g - min(pre)) * 1e-6 if pre else None)
        out["slip_precursor_lead_ms"] = leads
        out.update(self._contact_scores(scene_truth, end_ns))
        return out

    def _contact_scores(self, scene_truth, end_ns) -> dict:
        """The contacts' events and the emissions' readings counted, and the run against
        the scene's truth (`ae_tactile.scoring.score_run`)."""
        out = {}
        out["contact_events"] = {
            EVENT_NAMES[int(k)]: sum(1 for s in self.contacts if s.msg.event_type == k)
            for k in (ContactEvent.TOUCH, ContactEvent.DETOUCH)
        }
        readings = {}
        for s in self.emissions:
            name = READING_NAMES.get(s.msg.reading, str(s.msg.reading))
            readings[name] = readings.get(name, 0) + 1
        out["emission_readings"] = readings
        out["truth"] = score_run(
            [(time_msg_to_ns(t.header.stamp), int(t.event_type),
              (t.position.x, t.position.y, t.position.z)) for t in self.truth],
            [(since, st) for _, st, since, _ in self.states],
            [(s.stamp_ns, int(s.msg.event_type)) for s in self.slip],
            scene_truth,
            [(s.stamp_ns, int(s.msg.event_type)) for s in self.contacts],
            end_ns,
        )
        return out


def two_hop_floor_ms(context=None, n: int = 300, timeout_s: float = 10.0) -> dict:
    """The rclpy floor: ping -> pong -> back (two hops, std_msgs/Empty) between two nodes of
    this process on their own executor; median / p99 / max of one-way (RTT / 2) in ms.

    What any rclpy pipeline pays at least for one hop pair; measured in the same run as
    the latency it is compared with."""
    kw = {"context": context} if context is not None else {}
    a = Node("ae_tactile_floor_ping", **kw)
    b = Node("ae_tactile_floor_pong", **kw)
    ex = SingleThreadedExecutor(**kw)
    ex.add_node(a)
    ex.add_node(b)
    try:
        pong = b.create_publisher(Empty, "ae_tactile_floor/pong", 10)
        b.create_subscription(Empty, "ae_tactile_floor/ping", lambda m: pong.publish(Empty()), 10)
        got = []
        a.create_subscription(
            Empty, "ae_tactile_floor/pong", lambda m: got.append(time.perf_counter_ns()), 10
        )
        ping = a.create_publisher(Empty, "ae_tactile_floor/ping", 10)
        t_end = time.monotonic() + timeout_s
        while (
            ping.get_subscription_count() < 1 or pong.get_subscription_count() < 1
        ) and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
        rtt = []
        for _ in range(n):
            k = len(got)
            t0 = time.perf_counter_ns()
            ping.publish(Empty())
            t_stop = time.monotonic() + 1.0
            while len(got) == k and time.monotonic() < t_stop:
                ex.spin_once(timeout_sec=0.1)
            if len(got) > k:
                rtt.append((got[-1] - t0) * 1e-6)
        if not rtt:
            return {}
        r = np.asarray(rtt)
        return {
            "median": float(np.median(r)),
            "p99": float(np.percentile(r, 99)),
            "max": float(r.max()),
            "samples": int(r.size),
            "what": "two rclpy hops (ping -> pong -> back), same process",
        }
    finally:
        ex.shutdown()
        a.destroy_node()
        b.destroy_node()


def _latency(seen: list) -> dict:
    """Median, p99 and max of receive - emission stamp [ms] ({} if none)."""
    lat = np.array([(s.received_ns - s.stamp_ns) * 1e-6 for s in seen])
    if not lat.size:
        return {}
    return {"median": float(np.median(lat)), "p99": float(np.percentile(lat, 99)),
            "max": float(lat.max()), "n": int(lat.size)}


def _truth_lines(tr: dict | None, ce: dict) -> list:
    """The summary's lines scoring the run against the scene's truth."""
    if not tr:
        return []
    c = tr["contacts"]
    share = tr["state_right_share"]
    lines = [
        f"contacts: {ce.get('TOUCH', 0)} TOUCH / {ce.get('DETOUCH', 0)} DETOUCH published; "
        f"the scene's truth: {c['truth_begun']} contacts begun, {c['truth_ended']} ended",
        "contact state vs truth: "
        + ("n/a" if share is None else f"right {100 * share:.1f} % of the time")
        + f" ({tr['state_scored_s']:.2f} s scored, 0.1 s after each change excepted)",
        f"slip alarms: {tr['true_alarms']} backed by the truth, {tr['false_alarms']} false"
        + ("" if not tr["false_alarms"] else " (" + ", ".join(
            f"{k} at {t:.3f} s" for t, k in tr["false_alarm_list"][:8])
            + (", ..." if tr["false_alarms"] > 8 else "") + ")"),
    ]
    for g in tr["gross_slips"]:
        d, lead = g["slip_delay_ms"], g["precursor_lead_ms"]
        lines.append(
            f"gross slip ({g['part'] or 'scene'}): SLIP "
            + ("none" if d is None else (f"{-d:.0f} ms before" if d < 0 else f"{d:.0f} ms after"))
            + ", precursor lead " + ("none" if lead is None else f"{lead:.0f} ms"))
    return lines


def format_summary(s: dict) -> str:
    e = s["emissions"]
    tr = s["touch_release"]
    lines = [
        "",
        "=== summary ===",
        f"emissions captured by the device: {e['truth']}  "
        f"(not captured: {s['truth_not_captured_by_device']})",
        f"localized: found {e['matched']}, missed {e['truth'] - e['matched']}, "
        f"false {e['events'] - e['matched']}  "
        f"(recall {e['recall']:.3f}, precision {e['precision']:.3f})",
        f"touch/release: {tr['found']}/{tr['truth']} found, "
        f"{tr['typed_correctly']} typed correctly",
        f"RMS position error: {e['rms_position_error_mm'] * 1e3:.1f} um",
    ]
    if s["slip_events"]:
        lines.append(
            "slip detector: " + ", ".join(f"{k} x{v}" for k, v in sorted(s["slip_events"].items()))
        )
    for lead in s["slip_precursor_lead_ms"]:
        lines.append(
            "slip precursor lead time: "
            + ("none before gross slip" if lead is None else f"{lead:.0f} ms before gross slip")
        )
    if s.get("emission_readings"):
        lines.append("emissions read as: " + ", ".join(
            f"{k.lower()} x{v}" for k, v in sorted(s["emission_readings"].items())))
    lines += _truth_lines(s.get("truth"), s.get("contact_events", {}))
    if s["latency_ms"]:
        la = s["latency_ms"]
        lines.append(
            f"end-to-end latency (emission -> TOUCH, slip event or emission received): "
            f"median {la['median']:.2f} ms, p99 {la['p99']:.2f} ms"
        )
        dt = s.get("latency_by_kind_ms", {}).get("DETOUCH")
        if dt:
            lines.append(f"DETOUCH after the release's emission (its confirmation): median "
                         f"{dt['median']:.0f} ms")
    fl = s.get("floor_two_hop_ms")
    if fl:
        line = (
            f"rclpy floor, same run (two bare hops, empty message): median {fl['median']:.3f} ms, "
            f"p99 {fl['p99']:.3f} ms"
        )
        if s["latency_ms"] and fl["median"] > 0:
            line += f"  (latency / floor: {s['latency_ms']['median'] / fl['median']:.0f}x median)"
        lines.append(line)
    return "\n".join(lines)
