# SPDX-License-Identifier: Apache-2.0
"""Coincidence across the fingertips of one hand (ae_tactile.dsp.coincidence): one
electrical event seen by several fingertips is interference, an apex touch at a time of its
own is kept, at the rate Poisson statistics give; and the hand trial that runs it behind
each fingertip's packet tests (ae_eval.slip.hand_interference_trial)."""

import math

import numpy as np
import pytest

from ae_eval import slip as ev
from ae_tactile.dsp.coincidence import HandCoincidence

MS = 1_000_000


def test_a_burst_seen_by_another_fingertip_is_rejected_a_lone_packet_kept():
    hc = HandCoincidence(window_s=3e-4, wait_s=5e-3)
    hc.add_others([100 * MS + 250_000])  # 0.25 ms after this fingertip's stamp
    assert hc.hold(100 * MS, "burst") and hc.hold(200 * MS, "touch")
    assert hc.due(104 * MS) == ([], [])  # the burst's wait is not over
    assert hc.next_due_ns() == 105 * MS
    assert hc.due(105 * MS) == ([], ["burst"])
    hc.add_others([200 * MS + 350_000])  # outside the window
    assert hc.due(205 * MS) == (["touch"], [])
    assert hc.counts["kept"] == 1 and hc.counts["rejected_coincidence"] == 1
    assert hc.pending == 0 and hc.next_due_ns() is None


def test_a_report_after_the_decision_does_not_change_it_and_is_counted_late():
    hc = HandCoincidence(window_s=3e-4, wait_s=5e-3)
    hc.hold(10 * MS, "a")
    assert hc.due(15 * MS) == (["a"], [])
    hc.add_others([10 * MS])
    assert hc.counts["reports_late"] == 1
    hc.hold(30 * MS, "b")  # held out of order: decided in onset order
    hc.hold(20 * MS, "c")
    hc.add_others([30 * MS + 100_000])
    assert hc.due(40 * MS) == (["c"], ["b"])


def test_apex_touches_are_kept_at_the_poisson_rate():
    """Reports of the other fingertips at random times, 200 / s: a touch at a time of its
    own is kept with probability exp(-2 window lambda) = 0.887 for a 0.3 ms window."""
    rng = np.random.default_rng(5)
    lam, dur_s, w = 200.0, 100.0, 3e-4
    hc = HandCoincidence(window_s=w, wait_s=5e-3, keep_s=2 * dur_s)
    hc.add_others(np.sort(rng.uniform(0, dur_s, rng.poisson(lam * dur_s))) * 1e9)
    n = 20_000
    for i, t in enumerate(np.sort(rng.uniform(0.01, dur_s - 0.01, n))):
        hc.hold(t * 1e9, i)
    kept, rejected = hc.due(int(2 * dur_s * 1e9))
    p = math.exp(-2 * w * lam)
    assert len(kept) + len(rejected) == n
    assert abs(len(kept) / n - p) <= 4 * math.sqrt(p * (1 - p) / n)


def test_bad_stamps_are_counted_and_bad_settings_refused():
    hc = HandCoincidence()
    assert not hc.hold(float("nan"), "x") and not hc.hold("soon", "y")
    hc.add_others([np.nan, np.inf, 1.0e9])
    assert hc.counts["rejected_nonfinite"] == 4 and hc.pending == 0
    assert hc.coincident([1.0e9 + 1e5]).tolist() == [True]
    for kw in ({"window_s": 0.0}, {"window_s": math.nan}, {"window_s": 1e-3, "wait_s": 1e-4},
               {"wait_s": 2.0}, {"keep_s": 1e-3}):
        with pytest.raises(ValueError):
            HandCoincidence(**kw)
    assert HandCoincidence(wait_s=1.0).keep_ns == 2 * 10**9  # the reports outlive the wait


@pytest.fixture(scope="module")
def hand_rows():
    return [r for s in (0, 3, 7) for r in ev.hand_interference_trial(s, duration_s=0.5)]


def test_a_hand_rejects_interference_without_wall_echoes_and_keeps_apex_touches(hand_rows):
    """Bursts into the amplifier's input of fingertips without wall echoes (seeds 0, 3, 7:
    22 Hz and 3.5 kHz at random times, 201 Hz at random times) are apex touches to each
    fingertip's packet tests; the hand's coincidence leaves no phantom event, no extra
    contact, no alarm, keeps every acoustic packet and, below 100 bursts / s, nearly every
    apex touch (the Poisson cost: 1 - exp(-2 window rate) ~ 1.3 % at 22 Hz)."""
    rows = hand_rows
    assert all(not r["echoes"] and r["coupling"] == "input" for r in rows)
    assert all(not r["periodic"] for r in rows)  # the timing test cannot catch them
    assert sum(r["n_rejected_coincidence"] for r in rows) >= 100
    assert sum(r["n_phantom_events"] for r in rows) == 0
    assert all(r["contacts_created"] == 1 for r in rows)
    assert sum(r["n_alarm_onsets"] for r in rows) == 0
    assert all(r["n_acoustic_kept"] == r["n_acoustic_packets"] for r in rows)
    slow = [r for r in rows if r["rate_hz"] < 100]
    n_touch = sum(r["n_apex_touches"] for r in slow)
    assert n_touch >= 4 and sum(r["n_apex_touches_kept"] for r in slow) >= n_touch - 1
    err = np.concatenate([r["stamp_error_us"] for r in rows])
    assert err.size and np.all(np.abs(err) < 600)  # the links' floors: 50 .. 500 us
    assert all(r["offsets_learnt"] == r["n_fingers"] - 1 for r in rows if r["rate_hz"] > 100)


def test_without_the_hand_the_same_bursts_become_phantom_touches(hand_rows):
    """The control: the same hands, each fingertip alone (no coincidence), take a third or
    more of those bursts for apex touches: extra contacts."""
    rows = hand_rows
    n = sum(r["n_interference"] for r in rows)
    assert sum(r["alone_phantom_events"] for r in rows) >= 0.3 * n > 0
    assert sum(r["alone_contacts_created"] - 1 for r in rows) >= len(rows)
    assert sum(r["n_phantom_events"] for r in rows) == 0


def test_the_pipeline_holds_apex_packets_for_the_hand_and_hands_out_the_touches():
    """`ContactPipeline` on the hand: switching edges entering the amplifier's input (no
    echo test: one packet cannot tell) and touches within 0.4 mm of the apex (< 3 deg), all
    localized at the apex. Their onsets go out for the other fingertips; the packets are
    held for the wait; those another fingertip reported (the edges, 0.1 ms off on its
    clock) are dropped and counted, the touches handed out and through the slip step."""
    from ae_tactile.pipeline import ContactPipeline, PacketLocalizer, PacketView, SlipStage
    from ae_tactile.sim import SimConfig
    from ae_tactile.sim.interference import render_interference
    from ae_tactile.sim.scene import reference_noise_rms

    cfg = SimConfig()
    rng = np.random.default_rng(4)
    noise = reference_noise_rms(cfg, 30.0)
    apex = ev.apex_touch_packets(cfg, 12, noise, rng, radius_m=0.4e-3)  # < 3 deg
    edges = render_interference(30, cfg, kind="edge", coupling="input", noise_rms_v=noise,
                                rng=rng)
    fs = cfg.sample_rate_hz
    t_edge = 10**9 + np.sort(rng.choice(10**6, len(edges), replace=False)) * 1000
    # touches at random times (at multiples of one interval they would be a periodic train)
    t_touch = 3 * 10**9 + np.sort(rng.choice(10**6, len(apex), replace=False)) * 997
    views = [PacketView(edges.samples_v[i], fs, int(edges.onset_index[i]), int(t_edge[i]), i)
             for i in range(len(edges))]
    views += [PacketView(apex.samples_v[i], fs, int(apex.onset_index[i]), int(t_touch[i]),
                         100 + i) for i in range(len(apex))]
    pipe = ContactPipeline(PacketLocalizer("ml"), SlipStage())
    pipe.enable_hand(window_s=3e-4, wait_s=5e-3)
    out = []
    pipe.process(views, out.extend)
    assert out == []  # every packet lies at the apex, and no echo test runs yet
    onsets = pipe.take_apex_onsets()
    onset_of = {int(v.stamp_ns + v.onset_index * 1e9 / fs) for v in views}
    assert len(onsets) >= 0.8 * len(views) and set(onsets) <= onset_of
    assert pipe.take_apex_onsets() == []
    pipe.hand_reports(t_edge + np.round(edges.onset_index * 1e9 / fs).astype(np.int64) + 100_000)
    assert not pipe.idle() and not pipe.release_coincidence(10**9)  # nothing due yet
    assert pipe.release_coincidence(4 * 10**9)
    ids = {r.packet_ids[0] for r in out}
    counts = pipe.all_counts()
    assert ids <= set(range(100, 100 + len(apex))) and len(ids) >= 0.8 * len(apex)
    assert counts["rejected_INTERFERENCE_HAND"] == counts["hand_held"] - len(ids) > 0
    assert counts["hand_rejected_coincidence"] == counts["rejected_INTERFERENCE_HAND"]
    assert pipe.slip.counts["contacts_in"] == len(out) and pipe.idle()


def _play(hc, events):
    """Play (host ns, order, kind, payload) events through ``hc`` in time order: own onsets,
    held packets, the others' reports ((stamp, name)) and decisions; (kept, rejected)."""
    kept, rejected = [], []
    for t, _, kind, p in sorted(events, key=lambda e: (e[0], e[1])):
        if kind == "own":
            hc.add_own([p])
        elif kind == "hold":
            hc.hold(*p)
        elif kind == "report":
            hc.add_others([p[0]], p[1])
        else:
            k, r = hc.due(int(t))
            kept += k
            rejected += r
    return kept, rejected


def test_each_fingertips_clock_offset_is_learnt_from_the_common_bursts():
    """Two other fingertips whose links stamp every burst 0.44 ms late and 0.25 ms early
    (their latency floors): the first bursts fall outside the 0.3 ms window and are kept;
    once 8 bursts have paired, each fingertip's offset is known to a few microseconds and
    every later burst is rejected. Touches at times of their own are kept."""
    rng = np.random.default_rng(8)
    bursts = np.sort(rng.uniform(0, 2e9, 400)).astype(np.int64)  # 200 / s, random times
    touches = np.sort(rng.uniform(0, 2e9, 20)).astype(np.int64)
    hc = HandCoincidence(window_s=3e-4, wait_s=5e-3, keep_s=5.0)
    events = [(t, 0, "own", t) for t in bursts] + [(t, 0, "own", t) for t in touches]
    events += [(t, 1, "hold", (t, "b")) for t in bursts] + [(t, 1, "hold", (t, "t"))
                                                            for t in touches]
    for name, off in (("index", 440_000), ("thumb", -250_000)):
        jitter = rng.normal(0, 5_000, bursts.size).astype(np.int64)
        events += [(t + 800_000, 2, "report", (t + off + j, name))
                   for t, j in zip(bursts, jitter)]
    events += [(t + 5 * MS, 3, "due", None) for t in np.concatenate([bursts, touches])]
    kept, rejected = _play(hc, events)
    assert abs(hc.offsets_ns["index"] - 440_000) < 10_000
    assert abs(hc.offsets_ns["thumb"] + 250_000) < 10_000
    assert hc.counts["offsets_learnt"] == 2
    assert kept.count("b") <= 12 and rejected.count("b") >= len(bursts) - 12
    p_keep = math.exp(-2 * 3e-4 * 200 * 2)  # two fingertips' bursts at 200 / s
    assert kept.count("t") >= np.floor(len(touches) * p_keep) - 3


def test_a_fingertips_offset_that_moves_is_learnt_again_from_eight_bursts():
    """The other fingertip is re-plugged on another hub after 1 s: its link's latency floor,
    and so its stamps of the bursts, move from 0.44 ms late to 0.25 ms early. The newest 8
    pairs agree on the new offset while the 32 remembered still hold the old one: the 8th
    burst after the move (paired before it is decided) and every later one are rejected, at most 7
    pass; the move is counted once. Touches at times of their own pair with nothing that
    agrees and never move the offset."""
    rng = np.random.default_rng(11)
    bursts = np.sort(rng.uniform(0, 2e9, 400)).astype(np.int64)  # 200 / s, random times
    touches = np.sort(rng.uniform(0, 2e9, 40)).astype(np.int64)
    move_ns = 1_000_000_000
    hc = HandCoincidence(window_s=3e-4, wait_s=5e-3, keep_s=5.0)
    events = [(t, 0, "own", t) for t in np.concatenate([bursts, touches])]
    events += [(t, 1, "hold", (t, ("b", t))) for t in bursts]
    events += [(t, 1, "hold", (t, ("t", t))) for t in touches]
    jitter = rng.normal(0, 5_000, bursts.size).astype(np.int64)
    off = np.where(bursts < move_ns, 440_000, -250_000)
    events += [(t + 800_000, 2, "report", (t + o + j, "index"))
               for t, o, j in zip(bursts, off, jitter)]
    events += [(t + 5 * MS, 3, "due", None) for t in np.concatenate([bursts, touches])]
    kept, rejected = _play(hc, events)
    after = bursts[bursts >= move_ns]
    kept_after = sorted(t for kind, t in kept if kind == "b" and t >= move_ns)
    assert len(kept_after) <= 7
    assert not kept_after or kept_after[-1] < after[7]  # from the 8th burst on: rejected
    assert all(t in {r[1] for r in rejected} for t in after[7:])
    assert abs(hc.offsets_ns["index"] + 250_000) < 10_000
    assert hc.counts["offsets_learnt"] == 1 and hc.counts["offsets_moved"] == 1
    p_keep = math.exp(-2 * 3e-4 * 200)  # one other fingertip's bursts at 200 / s
    n_touch_kept = sum(1 for kind, _ in kept if kind == "t")
    assert n_touch_kept >= np.floor(len(touches) * p_keep) - 4


def test_a_release_never_overtakes_its_held_touch_and_the_held_are_flushed():
    """A touch at the apex (held for the hand: no echo test runs) and its release 1 ms
    later, localized just past 3 deg off the apex (not held), in the next batch: the
    release waits behind the touch and both go out in time order once the wait is over;
    the slip stage then sees a touch and its release (the finger free), not an orphan
    release and a touch that never ends. A touch still held when the driver stops goes
    out with `flush`."""
    from ae_tactile.pipeline import ContactPipeline, PacketLocalizer, SlipStage
    from ae_tactile.sim import SimConfig
    from ae_tactile.sim.scene import reference_noise_rms
    from ae_tactile.sim.triggered import render_triggered

    cfg = SimConfig()
    g = cfg.geometry
    fs = cfg.sample_rate_hz
    rng = np.random.default_rng(12)
    noise = reference_noise_rms(cfg, 30.0)
    # 2.3 deg (held: within 3 deg of the apex) and 3.7 deg (not held), 0.25 mm apart
    pts = g.surface_point_from_xy(np.array([0.4e-3, 0.65e-3, 0.1e-3]),
                                  np.array([0.0, 0.0, 0.2e-3]))
    r = render_triggered(pts, cfg, noise_rms_v=noise, rng=rng,
                         speed_m_s=np.array([0.3, 0.3, 0.3]), polarity=np.array([1, -1, 1]))
    t0 = 5 * 10**9
    stamps = [t0, t0 + MS, t0 + 400 * MS]
    views = [PacketViewFor(r, i, fs, stamps[i]) for i in range(3)]
    pipe = ContactPipeline(PacketLocalizer("ml"), SlipStage())
    pipe.enable_hand(window_s=3e-4, wait_s=5e-3)
    out = []
    pipe.process(views[:1], out.extend)  # the apex touch: held
    pipe.process(views[1:2], out.extend)  # its release off the apex: behind the touch
    assert out == [] and pipe.hand.pending == 2
    assert not pipe.release_coincidence(t0 + 2 * MS) and out == []
    assert pipe.release_coincidence(t0 + 10 * MS)
    assert [e.packet_ids[0] for e in out] == [0, 1]
    assert [e.time_ns for e in out] == sorted(e.time_ns for e in out)
    assert pipe.slip.counts["contacts_in"] == 2 and pipe.idle()
    assert pipe.tick(t0 + 200 * MS).state.name == "NO_CONTACT"
    pipe.process(views[2:], out.extend)  # another apex touch, then the driver stops
    assert pipe.hand.pending == 1 and len(out) == 2
    assert pipe.release_coincidence(t0 + 400 * MS, flush=True)
    assert [e.packet_ids[0] for e in out] == [0, 1, 2] and pipe.idle()


def PacketViewFor(r, i, fs, stamp_ns):
    from ae_tactile.pipeline import PacketView

    return PacketView(r.samples_v[i], fs, int(r.onset_index[i]), int(stamp_ns), i)


def test_reports_that_cannot_be_right_are_counted_and_change_nothing():
    """The hand's topic carries other nodes' messages: a stamp far from this fingertip's
    clock (a clock that jumped) is dropped and does not make the fingertip's real reports
    look old; a flood beyond the cap keeps the newest; a seventeenth name while sixteen are
    active is counted, a silent one forgotten; epoch stamps stay exact to the nanosecond."""
    now = 1_764_000_000 * 10**9  # an epoch stamp (2025): float64 would round it to 256 ns
    hc = HandCoincidence(window_s=1e-6, wait_s=5e-3)
    hc.add_others([now + 10**15], "index", now_ns=now)  # 11 days ahead
    hc.add_others([now - 3 * 10**9], "index", now_ns=now)  # 3 s old
    assert hc.counts["reports_rejected_stamp"] == 2
    hc.add_others([now - MS + 900], "index", now_ns=now)  # 0.9 us from the packet below
    assert hc.hold(now - MS, "burst") and hc.hold(now - MS + 2_000, "touch")
    assert hc.due(now + 10 * MS) == (["touch"], ["burst"])
    flood = now - np.arange(100_000, dtype=np.int64) * 5_000  # 0.5 s of 200 kHz
    hc.add_others(flood, "thumb", now_ns=now)
    assert hc.counts["reports_rejected_flood"] == 100_000 - 65_536
    for k in range(14):
        hc.add_others([now - 2 * MS], f"/f{k}", now_ns=now)
    assert len(hc._others) == 16
    hc.add_others([now], "/f99", now_ns=now + 10 * MS)
    assert hc.counts["reports_rejected_sources"] == 1 and "/f99" not in hc._others
    later = now + 2 * 10**9  # the others silent for 2 s: forgotten for a new name
    hc.add_others([later], "/f99", now_ns=later)
    assert set(hc._others) == {"/f99"}
    bad = hc.counts["rejected_nonfinite"]
    hc.add_others([True, False], "/f99")  # not stamps
    hc.add_others(["123", "4.5"], "/f99")
    hc.add_others([2**70, later + 1], "/f99")  # one beyond int64: the good one stays exact
    assert not (hc.hold(True, "x") or hc.hold("12", "y"))
    assert hc.counts["rejected_nonfinite"] == bad + 7
    assert int(hc._others["/f99"][-1]) == later + 1
    hc.add_others([later], "/f99", now_ns=2**70)  # no clock reads that: nothing checked
    assert hc.counts["reports_rejected_stamp"] == 3


def test_a_late_report_is_counted_only_for_a_packet_that_was_kept():
    """Three fingertips: the second one's report rejects the burst; the third one's,
    coming after the decision, changes nothing and is not late for it. A report after a
    kept packet's decision is late (that packet went out)."""
    hc = HandCoincidence(window_s=3e-4, wait_s=5e-3)
    hc.add_others([100 * MS + 50_000], "middle")
    hc.hold(100 * MS, "burst")
    hc.hold(200 * MS, "touch")
    assert hc.due(210 * MS) == (["touch"], ["burst"])
    hc.add_others([100 * MS + 80_000], "ring")
    assert hc.counts["reports_late"] == 0
    hc.add_others([200 * MS + 80_000], "ring")
    assert hc.counts["reports_late"] == 1


def test_records_behind_a_held_packet_go_out_after_it_in_time_order():
    """`follow`: a record later than a held packet waits for its decision (kept or not),
    one earlier than every held packet is not held back."""
    key = lambda r: r[0]  # noqa: E731
    hc = HandCoincidence(window_s=3e-4, wait_s=5e-3)
    hc.add_others([100 * MS + 10_000], "middle")
    hc.hold(100 * MS, (100 * MS, "burst"))
    hc.hold(104 * MS, (104 * MS, "touch"))
    hc.follow((103 * MS, "release of an earlier touch"))
    hc.follow((106 * MS, "off-apex touch"))
    assert hc.pending == 4
    assert hc.due(103 * MS, key) == ([], [])
    kept, rejected = hc.due(105 * MS, key)  # the burst is decided, the touch still held
    assert rejected == [(100 * MS, "burst")]
    assert kept == [(103 * MS, "release of an earlier touch")]
    kept, _ = hc.due(109 * MS, key)
    assert kept == [(104 * MS, "touch"), (106 * MS, "off-apex touch")] and hc.pending == 0


def test_the_offsets_are_learnt_when_no_apex_packet_is_held():
    """A fingertip whose own tests reject every burst (switching spikes after the filters:
    the shape test) holds nothing, yet its onsets still pair with the other fingertip's
    reports: the offset is learnt, ready for bursts its own tests would let through."""
    from ae_tactile.pipeline import ContactPipeline, PacketLocalizer, SlipStage
    from ae_tactile.sim import SimConfig
    from ae_tactile.sim.interference import render_interference
    from ae_tactile.sim.scene import reference_noise_rms

    cfg = SimConfig()
    rng = np.random.default_rng(6)
    noise = reference_noise_rms(cfg, 30.0)
    spikes = render_interference(40, cfg, kind="ringing", coupling="adc", noise_rms_v=noise,
                                 rng=rng)
    fs = cfg.sample_rate_hz
    t = 10**9 + np.sort(rng.choice(10**6, len(spikes), replace=False)) * 1000
    views = [PacketViewFor(spikes, i, fs, t[i]) for i in range(len(spikes))]
    pipe = ContactPipeline(PacketLocalizer("ml"), SlipStage())
    pipe.enable_hand(window_s=3e-4, wait_s=5e-3)
    out = []
    pipe.process(views, out.extend)
    onsets = np.asarray(pipe.take_apex_onsets(), np.int64)
    assert out == [] and pipe.hand.counts["held"] == 0 and onsets.size >= 20
    pipe.hand_reports(onsets + 440_000, "index")
    pipe.release_coincidence(int(t[-1]) + 10 * MS)
    assert pipe.hand.counts["offsets_learnt"] == 1
    assert abs(pipe.hand.offsets_ns["index"] - 440_000) < 1_000
