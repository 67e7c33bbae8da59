# SPDX-License-Identifier: Apache-2.0
"""The hot-path core (ae_tactile.pipeline), without ROS: simulated packets in, contact and
slip events out, scored against the simulator's ground truth; bad packets rejected one by
one and counted; the single-packet and batched paths agree."""

import functools
import math
import os

import numpy as np
import pytest

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.pipeline import (
    OVERLAP_INLINE_MAX,
    ContactPipeline,
    EventType,
    PacketLocalizer,
    PacketView,
    SlipStage,
    packet_problem,
)
from ae_tactile.sim import SimConfig
from ae_tactile.sim.triggered import render_triggered
from ae_tactile.slip import SlipConfig

FS = 10e6


def _packets(n=24, seed=3, snr_db=30.0, polarity=1):
    geo = FingertipGeometry()
    rng = np.random.default_rng(seed)
    rho = 6e-3 * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    pts = geo.surface_point_from_xy(rho * np.cos(phi), rho * np.sin(phi))
    tp = render_triggered(pts, SimConfig(), snr_db=snr_db, polarity=polarity, rng=seed)
    t0 = 1_000_000_000
    views = [
        PacketView(
            tp.samples_v[i].astype(np.float32),
            tp.sample_rate_hz,
            int(tp.onset_index[i]),
            t0 + i * 10_000_000,
            i,
        )
        for i in range(n)
    ]
    emission_ns = [t0 + i * 10_000_000 + int(round(tp.emission_time_s[i] * 1e9)) for i in range(n)]
    return views, tp.points_m, emission_ns


def test_contact_events_match_the_ground_truth_in_space_time_and_type():
    views, truth, emission_ns = _packets()
    loc = PacketLocalizer("ml")
    events = loc.process(views)
    assert len(events) == len(views) and loc.counts["events"] == len(views)
    err = np.array([math.dist(e.point_m, p) for e, p in zip(events, truth)])
    assert np.sqrt(np.mean(err**2)) < 50e-6  # 30 dB: tens of um (CRLB ~ 9 um)
    dt_ns = np.array([e.time_ns - t for e, t in zip(events, emission_ns)])
    assert np.all(np.abs(dt_ns) < 500)  # emission instant within 0.5 us
    assert all(e.event_type == EventType.TOUCH for e in events)
    assert [e.packet_ids for e in events] == [(v.sequence_id,) for v in views]
    released = PacketLocalizer("ml").process(_packets(8, seed=4, polarity=-1)[0])
    assert released and all(e.event_type == EventType.DETOUCH for e in released)


def test_single_packet_and_batched_paths_agree():
    views, _, _ = _packets(12, seed=9)
    one = PacketLocalizer("ml", batch_min=10_000)  # every packet alone
    many = PacketLocalizer("ml", batch_min=1)  # one batch
    a, b = one.process(views), many.process(views)
    assert len(a) == len(b) == len(views)
    for x, y in zip(a, b):
        assert math.dist(x.point_m, y.point_m) < 2e-6
        assert abs(x.time_ns - y.time_ns) < 20
        assert x.event_type == y.event_type


@pytest.mark.parametrize(
    "bad", ["fs0", "fs_nan", "fs_neg", "fs_inf", "fs_1hz", "fs_150khz", "fs_1e11", "long",
            "short", "shape", "onset", "nan"]
)
def test_a_bad_packet_is_counted_and_costs_no_neighbour(bad):
    views, _, _ = _packets(6, seed=11)
    v = views[2]
    broken = {
        "fs0": dict(sample_rate_hz=0.0),
        "fs_nan": dict(sample_rate_hz=float("nan")),
        "fs_neg": dict(sample_rate_hz=-FS),
        "fs_inf": dict(sample_rate_hz=float("inf")),
        # valid numbers the localizer cannot use (issue 39: they raised from the band's
        # check and lost the whole batch) or that would cost gigabytes (issue 37)
        "fs_1hz": dict(sample_rate_hz=1.0),
        "fs_150khz": dict(sample_rate_hz=150e3),
        "fs_1e11": dict(sample_rate_hz=1e11),
        "long": dict(samples_v=np.zeros((4, 100_000), dtype=np.float32)),
        "short": dict(samples_v=v.samples_v[:, :3]),
        "shape": dict(samples_v=v.samples_v[:3]),
        "onset": dict(onset_index=10_000),
        "nan": dict(
            samples_v=np.where(np.arange(400) == 120, np.nan, v.samples_v).astype(np.float32)
        ),
    }[bad]
    views[2] = PacketView(**{**v.__dict__, **broken})
    for batch_min in (1, 10_000):
        loc = PacketLocalizer("ml", batch_min=batch_min)
        events = loc.process(views)
        assert [e.packet_ids[0] for e in events] == [0, 1, 3, 4, 5]
        rejected = {k: n for k, n in loc.counts.items() if k.startswith("rejected_")}
        assert sum(rejected.values()) == 1, rejected
        assert loc.counts["packets"] == 6


def test_packet_problem_names_the_defect():
    x = np.zeros((4, 400), np.float32)
    assert packet_problem(x, FS, 80) is None
    assert packet_problem(x, 0.0, 80) == "sample_rate"
    assert packet_problem(x[:, :4], FS, 1) == "too_short"
    assert packet_problem(x, FS, 400) == "onset"
    assert packet_problem(x.ravel(), FS, 1) == "shape"


def test_run_time_settings_take_effect_at_once():
    views, _, _ = _packets(6, seed=12, snr_db=20.0)
    loc = PacketLocalizer("ml")
    assert len(loc.process(views)) == 6
    loc.update(min_snr_db=60.0)  # nothing is that clean
    assert loc.process(views) == [] and loc.counts["rejected_LOW_SNR"] == 6
    loc.update(min_snr_db=5.0, min_confidence=1.01)
    assert loc.process(views) == [] and loc.counts["below_min_confidence"] == 6
    loc.update(min_confidence=0.0, method="gradient")
    assert len(loc.process(views)) == 6 and loc.method == "gradient"


def _slip_scene_packets():
    """The incipient-slip scene's packets (the virtual device's view), first 1.2 s."""
    import os

    from ae_tactile.sim.scene import load_scene

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sc = load_scene(os.path.join(root, "config", "scenes", "incipient_slip.yaml"))
    src = sc.triggered_source(pretrigger_s=8e-6, window_s=40e-6)
    views, k = [], 0
    while True:
        b = src.next_packets(256)
        if len(b) == 0:
            break
        for i in range(len(b)):
            start_ns = int(round(b.start_index[i] * 1e9 / b.sample_rate_hz))
            views.append(
                PacketView(b.samples_v[i], b.sample_rate_hz, int(b.onset_index[i]), start_ns, k)
            )
            k += 1
    gross = sc.truth.get("gross_slip_time_ns") if isinstance(sc.truth, dict) else None
    return views, sc, gross


def test_pipeline_reports_touches_before_slip_and_slip_events_name_the_deciding_packet():
    """The incipient-slip scene in read cycles: the contact's TOUCH goes out before any slip
    event of it, which carries its id; every localized emission goes out once on the
    emissions callback, with a reading, after the localizer handed it over."""
    from ae_tactile.records import Reading

    views, sc, _ = _slip_scene_packets()
    geo = sc.config.geometry
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=geo), SlipStage(SlipConfig()))
    order, slips, contacts, localized, emissions = [], [], [], [], []

    def on_contacts(cs):
        order.append(("contacts", len(cs)))
        contacts.extend(cs)

    def on_slip(ss):
        order.append(("slip", len(ss)))
        slips.extend(ss)

    def on_emissions(es):
        assert all(e.packet_ids[0] in {c.packet_ids[0] for c in localized} for e in es)
        emissions.extend(es)

    for i in range(0, len(views), 4):  # batches as a read cycle would give them
        pipe.process(views[i : i + 4], localized.extend, on_slip, on_contacts=on_contacts,
                     on_emissions=on_emissions)
    assert pipe.wait_idle(120.0)  # what waited for the overlap resolver's answers
    pipe.close()
    kinds = {s.event_type for s in slips}
    assert EventType.SLIP_PRECURSOR in kinds and EventType.SLIP in kinds
    first_slip = next(i for i, o in enumerate(order) if o[0] == "slip")
    assert order[first_slip - 1][0] == "contacts"  # the contact's TOUCH went out first
    touched = {c.contact_id for c in contacts if c.event_type == EventType.TOUCH}
    assert touched and 0 not in touched
    assert {s.contact_id for s in slips} <= touched
    ids = {v.sequence_id for v in views}
    for s in slips:
        assert s.packet_ids and s.packet_ids[-1] in ids
        assert all(np.isfinite(s.point_m))
    # the deciding packet is the newest one the event names
    assert all(s.packet_ids[-1] == max(s.packet_ids) for s in slips)
    # one emission record per localized emission, in the order of their slip step
    assert sorted(e.packet_ids for e in emissions) == sorted(c.packet_ids for c in localized)
    assert all(e.reading in set(Reading) for e in emissions)
    assert {e.contact_id for e in emissions if e.contact_id} <= touched


def test_the_slip_step_is_not_put_off_while_packets_wait():
    """The slip step decides a contact's TOUCH: it runs for each batch within its own
    `process` call even while the link says more packets wait, and gives the same events
    as without that signal, in the same order."""
    views, sc, _ = _slip_scene_packets()
    geo = sc.config.geometry

    def run(more_waiting):
        pipe = ContactPipeline(
            PacketLocalizer("ml", geometry=geo, resolve_overlaps=False), SlipStage(SlipConfig())
        )
        out, late = [], []
        for i in range(0, len(views), 4):
            batch_ids = {v.sequence_id for v in views[i : i + 4]}
            n = pipe.slip.counts["contacts_in"]

            def on_events(rs, batch_ids=batch_ids):
                late.extend(r for r in rs if r.packet_ids and r.packet_ids[-1] not in batch_ids
                            and r.event_type != EventType.DETOUCH)
                out.extend(rs)

            localized = []
            pipe.process(views[i : i + 4], localized.extend, on_events,
                         more_waiting=more_waiting, on_contacts=on_events)
            assert not pipe.slip_pending
            assert pipe.slip.counts["contacts_in"] - n == len(localized)  # all stepped
        assert not late
        return [(int(r.event_type), r.time_ns, r.packet_ids, r.contact_id) for r in out]

    immediate = run(None)
    assert sum(1 for r in immediate if r[0] == EventType.TOUCH) >= 1
    assert run(lambda: True) == immediate


def test_slip_stage_processes_late_events_within_the_tolerance_and_counts_older_ones():
    views, sc, _ = _slip_scene_packets()
    loc = PacketLocalizer("ml", geometry=sc.config.geometry)
    contacts = loc.process(views[:40])
    stage = SlipStage(SlipConfig(reorder_tolerance_s=0.05), lag_s=0.0)
    stage.process(contacts[:30])
    newest = contacts[29].time_ns
    stage.tick(newest)  # the clock reached the newest event
    late = contacts[30:]
    late_ok = [c for c in late if c.time_ns >= newest - 50_000_000]
    before = stage.all_counts().get("slip_rejected_out_of_order", 0)
    stage.process(late)
    after = stage.all_counts().get("slip_rejected_out_of_order", 0)
    assert after - before == len(late) - len(late_ok)
    too_old = [c for c in contacts[:5]]
    stage.tick(newest + 200_000_000)
    stage.process(too_old)
    counts = stage.all_counts()
    assert sum(v for k, v in counts.items() if "out_of_order" in k) >= len(too_old)


def test_common_mode_interference_is_rejected_and_counted_while_apex_touches_are_kept():
    from ae_tactile.sim.interference import render_interference

    geo = FingertipGeometry()
    cfg = SimConfig()
    apex = render_triggered(
        geo.surface_point_from_xy(
            np.array([0.0, 0.2e-3, -0.3e-3]), np.array([0.0, 0.1e-3, 0.2e-3])
        ),
        cfg,
        snr_db=30.0,
        rng=6,
    )
    bursts = render_interference(
        30, cfg, kind="mixed", coupling="adc", noise_rms_v=float(apex.noise_rms_v[0]), rng=5
    )
    views = [
        PacketView(bursts.samples_v[i], FS, int(bursts.onset_index[i]), i * 1_000_000, i)
        for i in range(len(bursts))
    ]
    views += [
        PacketView(apex.samples_v[i], FS, int(apex.onset_index[i]), 10**9 + i, 100 + i)
        for i in range(len(apex))
    ]
    loc = PacketLocalizer("ml")
    events = loc.process(views)
    kept = {e.packet_ids[0] for e in events}
    assert {100, 101, 102} <= kept  # the apex touches are kept
    assert not kept & set(range(len(bursts)))  # no burst became a contact
    rejected = sum(v for k, v in loc.counts.items() if k.startswith("rejected_"))
    assert rejected == len(bursts) and loc.counts["rejected_INTERFERENCE"] >= len(bursts) // 2


def _edge_and_apex_views(cfg, seed):
    """Switching edges entering the amplifier's input (packet ids 0..39) and touches within
    1 mm of the apex (ids 100..119), as packet views."""
    from ae_eval.slip import apex_touch_packets
    from ae_tactile.sim.interference import render_interference
    from ae_tactile.sim.scene import reference_noise_rms

    rng = np.random.default_rng(seed)
    noise = reference_noise_rms(cfg, 30.0)
    apex = apex_touch_packets(cfg, 20, noise, rng, radius_m=1e-3)
    edges = render_interference(40, cfg, kind="edge", coupling="input", noise_rms_v=noise, rng=rng)
    t_ns = np.sort(rng.integers(0, 10**9, len(edges)))  # at random times: no periodic train
    out = [
        PacketView(edges.samples_v[i], cfg.sample_rate_hz, int(edges.onset_index[i]),
                   int(t_ns[i]), i)
        for i in range(len(edges))
    ]
    out += [
        PacketView(apex.samples_v[i], cfg.sample_rate_hz, int(apex.onset_index[i]), 10**9 + i,
                   100 + i)
        for i in range(len(apex))
    ]
    return out, set(range(len(edges))), set(range(100, 100 + len(apex)))


def _off_apex_touch_views(cfg, n, seed):
    """``n`` touches 15 .. 40 deg from the apex at 30 dB (the device's everyday touches)."""
    from ae_tactile.sim.scene import reference_noise_rms

    rng = np.random.default_rng(seed)
    g = cfg.geometry
    pol = np.radians(rng.uniform(15, 40, n))
    az = rng.uniform(0, 2 * np.pi, n)
    pts = g.surface_point_from_xy(g.radius_m * np.sin(pol) * np.cos(az),
                                  g.radius_m * np.sin(pol) * np.sin(az))
    pk = render_triggered(pts, cfg, noise_rms_v=reference_noise_rms(cfg, 30.0), rng=rng,
                          speed_m_s=np.full(n, 0.3), polarity=np.ones(n, int))
    return [
        PacketView(pk.samples_v[i], cfg.sample_rate_hz, int(pk.onset_index[i]), i, 500 + i)
        for i in range(n)
    ]


def test_interference_through_the_front_end_needs_the_echo_test_of_a_device_with_echoes():
    """Switching edges entering the amplifier's input are shaped like an apex touch's
    packet; on a fingertip with wall echoes the missing echo at 2R/c gives them away once
    interference_echo_min is set (at run time), and apex touches, which have their echo,
    are still kept. Bad thresholds are refused, nothing changed."""
    cfg = SimConfig(reflections=True)
    views, edges, touches = _edge_and_apex_views(cfg, 11)
    # weak releases off: a weak packet's fate depends on the touches before it, and the
    # edges the first pass accepts are such touches (the two passes would differ by that)
    loc = PacketLocalizer(
        "ml", geometry=cfg.geometry, interference_echo_min=0.0, weak_releases=False
    )
    assert loc.echo_min_in_use is None and loc.echo_test_status() == "off"
    kept = {e.packet_ids[0] for e in loc.process(views)}
    assert len(kept & edges) >= len(edges) // 2  # without it: touches
    apex_kept = kept & touches
    assert len(apex_kept) >= 15  # (weak releases below the SNR threshold aside)
    loc.update(interference_echo_min=0.25)
    kept = {e.packet_ids[0] for e in loc.process(views)}
    assert not kept & edges
    assert kept & touches == apex_kept
    for bad in (1.5, -1.5, float("nan")):
        with pytest.raises(ValueError):
            loc.update(interference_echo_min=bad)
        assert loc.interference_echo_min == 0.25
    with pytest.raises(ValueError):  # a bad value beside a good one: nothing changes
        loc.update(interference_echo_min=0.5, method="no_such_method")
    assert loc.interference_echo_min == 0.25 and loc.method == "ml"


@pytest.mark.parametrize("medium", ["water_skin", "silicone"])
def test_the_echo_test_is_learnt_from_the_devices_own_touches(medium):
    """By default the echo test learns the wall's echo from touches away from the apex:
    after three, on a fingertip with echoes (the simulator's wall returns -0.5 of the
    direct wave), the learnt echo is that ratio and input-coupled edges are rejected while
    apex touches are kept; on a fingertip without echoes the test stays off and keeps
    everything (the edges are then apex touches: no single packet tells them apart)."""
    from ae_tactile.pipeline import ECHO_MIN_LEARN

    for echoes in (True, False):
        cfg = SimConfig.for_medium(medium, reflections=echoes)
        views, edges, touches = _edge_and_apex_views(cfg, 12)
        loc = PacketLocalizer("ml", geometry=cfg.geometry)
        assert loc.interference_echo_min == ECHO_MIN_LEARN and loc.echo_min_in_use is None
        assert loc.echo_test_status().startswith("learning")
        before = {e.packet_ids[0] for e in loc.process(views)}
        assert len(before & edges) >= len(edges) // 2  # not yet learnt: edges pass
        apex_kept = before & touches
        assert len(apex_kept) >= 15
        learnt = loc.process(_off_apex_touch_views(cfg, 3, 5))
        assert len(learnt) == 3
        kept = {e.packet_ids[0] for e in loc.process(views)}
        assert kept & touches == apex_kept
        if echoes:
            ratio = loc.echo_learner.ratio
            assert ratio == pytest.approx(abs(cfg.reflection_coefficient), abs=0.05)
            assert loc.echo_min_in_use == pytest.approx(0.5 * ratio)
            assert loc.echo_test_status().startswith("learnt")
            assert not kept & edges
        else:
            assert loc.echo_learner.ratio < 0.05 and loc.echo_min_in_use is None
            assert "no wall echo" in loc.echo_test_status()
            assert kept & edges == before & edges
        loc.update(geometry=FingertipGeometry(radius_m=0.012))  # another body: learn again
        assert loc.echo_learner.ratio is None


@pytest.mark.parametrize("fs", [2e6, 10e6])
def test_a_periodic_burst_train_is_rejected_by_its_timing_on_a_device_without_echoes(fs):
    """No wall echo, edges entering the amplifier's input at 1 kHz (an apex touch's packet,
    each one): from the 4th burst on, their timing gives them away (counted apart); apex
    touches at random times among them are all kept (those above the SNR threshold)."""
    from ae_eval.slip import apex_touch_packets
    from ae_tactile.sim.interference import render_interference
    from ae_tactile.sim.scene import reference_noise_rms

    cfg = SimConfig(sample_rate_hz=fs)
    rng = np.random.default_rng(21)
    noise = reference_noise_rms(cfg, 30.0)
    n = 50
    edges = render_interference(n, cfg, kind="edge", coupling="input", noise_rms_v=noise, rng=rng)
    apex = apex_touch_packets(cfg, 30, noise, rng, radius_m=1.5e-3)
    t_edge = 0.0123 + 1e-3 * np.arange(n)
    t_apex = rng.uniform(0.0, 0.05, 30)
    order = sorted(
        [(t, 0, i) for i, t in enumerate(t_edge)] + [(t, 1, i) for i, t in enumerate(t_apex)]
    )
    loc = PacketLocalizer("ml", geometry=cfg.geometry)
    kept_edges, kept_apex = [], []
    for t, is_touch, i in order:
        pk = apex if is_touch else edges
        on = int(pk.onset_index[i])
        view = PacketView(pk.samples_v[i], fs, on, int(round((t - on / fs) * 1e9)), i)
        if loc.process([view]):
            (kept_apex if is_touch else kept_edges).append(i)
    assert set(kept_edges) <= {0, 1, 2}
    c = loc.counts  # the packet tests catch some (2 MS/s: most), the timing the others
    assert c["rejected_INTERFERENCE_TRAIN"] > 0
    assert c["rejected_INTERFERENCE_TRAIN"] + c["rejected_INTERFERENCE"] >= 0.9 * (n - 3)
    assert len(kept_apex) + loc.counts["rejected_LOW_SNR"] >= 30  # every other one kept



def test_a_crystal_timed_tapping_rig_keeps_its_touches_with_the_timing_test_off():
    """Acoustic touches within 0.4 mm of the apex (< 3 deg: the packets the timing test
    watches) at exactly 20 ms intervals (a calibration rig) on a device
    without echoes: by default the timing test takes them for a periodic train from the
    4th on (its documented cost); with interference_timing off every touch above the SNR
    threshold is kept, and switching it back on at run time brings the test back."""
    from ae_eval.slip import apex_touch_packets
    from ae_tactile.sim.scene import reference_noise_rms

    cfg = SimConfig(sample_rate_hz=5e6)
    rng = np.random.default_rng(5)
    n = 12
    apex = apex_touch_packets(cfg, n, reference_noise_rms(cfg, 30.0), rng, radius_m=0.4e-3)

    def run(loc, t0_s):
        kept = 0
        for i in range(n):
            on = int(apex.onset_index[i])
            t = t0_s + 0.02 * i
            view = PacketView(apex.samples_v[i], 5e6, on, int(round((t - on / 5e6) * 1e9)), i)
            kept += len(loc.process([view]))
        return kept

    default = PacketLocalizer("ml", geometry=cfg.geometry)
    kept = run(default, 0.01)
    assert kept <= 3  # the first three make the train
    assert default.counts["rejected_INTERFERENCE_TRAIN"] >= n - 3 - default.counts[
        "rejected_INTERFERENCE"] - default.counts["rejected_LOW_SNR"]
    rig = PacketLocalizer("ml", geometry=cfg.geometry, interference_timing=False)
    kept = run(rig, 0.01)
    assert rig.counts["rejected_INTERFERENCE_TRAIN"] == 0
    assert kept + rig.counts["rejected_LOW_SNR"] + rig.counts["rejected_INTERFERENCE"] == n
    assert rig.counts["rejected_INTERFERENCE"] <= 1 and kept >= n // 2  # weak ones: LOW_SNR
    rig.update(interference_timing=True)
    weak = rig.counts["rejected_LOW_SNR"]
    run(rig, 1.01)  # the same rig a second later: a train again
    weak = rig.counts["rejected_LOW_SNR"] - weak
    assert rig.counts["rejected_INTERFERENCE_TRAIN"] >= n - 3 - weak


def test_the_common_mode_screen_costs_no_touch_of_a_slip_near_the_apex(monkeypatch):
    """A contact slipping at the apex (gross slip at 1 kHz, many windows holding two
    emissions: common-mode to the screen, but a single template cannot explain them): the
    screen's spectrum tests reject none of them; what is rejected as interference is what
    the apex tests rejected without the screen."""
    import ae_tactile.pipeline.screens as pl
    from ae_tactile.sim.scene import load_scene

    spec = {"generator": "incipient_slip", "duration_s": 1.2, "seed": 3,
            "sensor": {"medium": "water_skin"}, "effects": {"reflections": True},
            "noise": {"snr_db": 30.0},
            "params": {"x_m": 0.0, "y_m": 0.0, "tangential_load_rate_n_per_s": 2.0,
                       "slip_rate_hz": 1000.0, "start_s": 0.05}}
    scene = load_scene(spec)
    pk = scene.triggered_source().next_packets(1 << 30, horizon_ns=int(1.2e9))
    fs = scene.config.sample_rate_hz
    views = [PacketView(pk.samples_v[i].astype(np.float32), fs, int(pk.onset_index[i]),
                        int(rng_t), i, noise_rms_v=float(scene.noise_rms_v))
             for i, rng_t in enumerate(np.sort(np.random.default_rng(1).integers(0, 10**12,
                                                                                 len(pk.emissions))))]

    def rejected(screen):
        monkeypatch.setattr(pl, "COMMON_SUSPECT", pl.COMMON_SUSPECT if screen else 2.0)
        loc = PacketLocalizer("ml", geometry=scene.config.geometry)
        for v in views:
            loc.process([v])
        return loc.counts["rejected_INTERFERENCE"], loc.counts["events"]

    with_screen, without = rejected(True), rejected(False)
    assert len(views) > 500 and with_screen == without


def test_the_pipeline_learns_the_echo_after_handing_out_the_contact_events():
    """In the live pipeline the echo is measured after the contact events are out (or, with
    packets waiting, when the link is idle), and then guards the apex the same way."""
    cfg = SimConfig(reflections=True)
    loc = PacketLocalizer("ml", geometry=cfg.geometry)
    pipe = ContactPipeline(loc, SlipStage(SlipConfig()))
    seen = []

    def out(contacts):
        seen.append((len(contacts), loc.echo_learner.n_measured))

    touches = _off_apex_touch_views(cfg, 3, 8)
    pipe.process(touches[:1], out)
    assert seen == [(1, 0)] and loc.echo_learner.n_measured == 1  # learnt after the event
    pipe.process(touches[1:], out, more_waiting=lambda: True)
    assert loc.echo_pending and loc.echo_learner.n_measured == 1  # packets waiting: later
    pipe.run_idle_work()
    assert not loc.echo_pending and loc.echo_learner.echo_min is not None
    views, edges, touches_apex = _edge_and_apex_views(cfg, 13)
    got = []
    pipe.process(views, got.extend)
    kept = {e.packet_ids[0] for e in got}
    assert not kept & edges and len(kept & touches_apex) >= 15
    pipe.close()


def test_an_echo_still_being_learnt_judges_the_next_batch_when_the_reader_is_behind():
    """The device's first three touches come in one batch while more packets wait (the
    reader behind): their echo is learnt before the next batch is judged, so the
    input-coupled edges in it are rejected and the apex touches kept. While the device's
    acoustic packet is still being learnt the next batches are measured too; once both
    are learnt, further measurements wait for a moment without packets again."""
    from ae_tactile.dsp.acoustic_model import LEARN_KEEP

    cfg = SimConfig(reflections=True)
    loc = PacketLocalizer("ml", geometry=cfg.geometry)
    pipe = ContactPipeline(loc, SlipStage(SlipConfig()))
    behind = lambda: True  # noqa: E731
    pipe.process(_off_apex_touch_views(cfg, 3, 8), lambda c: None, more_waiting=behind)
    assert loc.echo_pending and loc.echo_learner.ratio is None  # not yet: packets waiting
    views, edges, touches_apex = _edge_and_apex_views(cfg, 13)
    got = []
    pipe.process(views, got.extend, more_waiting=behind)
    assert loc.echo_test_status().startswith("learnt")
    kept = {e.packet_ids[0] for e in got}
    assert not kept & edges and len(kept & touches_apex) >= 15
    n = loc.echo_learner.n_measured
    pipe.process(_off_apex_touch_views(cfg, 2, 9), lambda c: None, more_waiting=behind)
    assert loc.screens.acoustic.n_learnt < LEARN_KEEP  # still learning: measured at once
    pipe.process(_off_apex_touch_views(cfg, 1, 10), lambda c: None, more_waiting=behind)
    assert loc.echo_learner.n_measured > n
    for seed in range(11, 11 + 4 * LEARN_KEEP):  # the acoustic model fills
        if loc.screens.acoustic.n_learnt >= LEARN_KEEP:
            break
        pipe.process(_off_apex_touch_views(cfg, 4, seed), lambda c: None, more_waiting=behind)
    assert loc.screens.acoustic.n_learnt >= LEARN_KEEP
    pipe.process(_off_apex_touch_views(cfg, 2, 3), lambda c: None, more_waiting=behind)
    n = loc.echo_learner.n_measured
    pipe.process(_off_apex_touch_views(cfg, 2, 4), lambda c: None, more_waiting=behind)
    assert loc.echo_pending and loc.echo_learner.n_measured == n  # learnt: later, when idle
    pipe.close()


@pytest.mark.parametrize("inline_max", [OVERLAP_INLINE_MAX, 2])
def test_overlapping_emissions_are_resolved_in_the_reader_or_worker_naming_the_shared_packet(
    inline_max,
):
    """Two emissions 2-8 us apart in each of six windows of one batch: the first
    ``overlap_inline_max`` windows are answered in the caller's thread, the others by the
    resolver's worker process; no wrong point is published, and both emissions of each
    window come, each within 0.1 mm, naming the shared packet."""
    import threading

    from ae_eval.overlap_trials import simulate_overlaps

    cfg = SimConfig(reflections=True)
    d = simulate_overlaps(
        6,
        cfg,
        separation_s=np.array([2e-6, 3e-6, 4e-6, 5e-6, 6e-6, 8e-6]),
        amplitude_ratio=1.0,
        snr_db=30.0,
        rng=3,
    )
    views = [
        PacketView(
            d["samples_v"][i], d["sample_rate_hz"], int(d["onset_index"][i]),
            (1 + i) * 10**9, 40 + i,
        )
        for i in range(6)
    ]
    got, in_reader, done = [], set(), threading.Event()
    caller = threading.get_ident()

    def on_contacts(recs):
        got.extend(recs)
        if threading.get_ident() == caller:  # handed out by process() itself
            in_reader.update(e.packet_ids for e in recs)
        if len(got) >= 12:
            done.set()

    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), None)
    pipe.overlap_inline_max = inline_max
    pipe.process(views, on_contacts)
    assert done.wait(300.0), (len(got), dict(pipe.all_counts()))
    counts = pipe.all_counts()
    assert counts["overlap_answered_in_reader"] == inline_max
    assert in_reader == {(40 + i,) for i in range(inline_max)}
    worker = pipe.overlaps._proc
    assert worker is not None and "overlap_worker_unavailable" not in counts
    pipe.close()
    assert worker.poll() is not None  # the worker process ended with the pipeline
    by_packet = {}
    for e in got:  # never a wrong point with a small sigma
        truth = d["points_m"][e.packet_ids[0] - 40]
        err = np.min(np.linalg.norm(truth - np.array(e.point_m), axis=1))
        assert err < 0.5e-3 or np.sqrt(np.trace(e.covariance_m2)) > err / 3
        by_packet.setdefault(e.packet_ids, []).append(e)
    solved = 0
    for (sid,), evs in by_packet.items():
        truth = d["points_m"][sid - 40]
        if len(evs) == 2:
            errs = [np.min(np.linalg.norm(truth - np.array(e.point_m), axis=1)) for e in evs]
            solved += all(x < 0.1e-3 for x in errs)
    assert solved >= 5, (solved, dict(counts))
    assert counts["overlap_windows_resolved"] >= 5


def _priority(tid: int) -> str:
    """How thread / process ``tid`` is scheduled against this thread: "idle" (SCHED_IDLE),
    "nice" (niceness 10 above), "same" (as this thread) or "other"."""
    if os.sched_getscheduler(tid) == os.SCHED_IDLE:
        return "idle"
    own, theirs = os.getpriority(os.PRIO_PROCESS, 0), os.getpriority(os.PRIO_PROCESS, tid)
    if os.sched_getscheduler(tid) != os.sched_getscheduler(0):
        return "other"
    return "nice" if theirs == min(own + 10, 19) else ("same" if theirs == own else "other")


@pytest.mark.parametrize("idle", [False, True])
def test_overlap_worker_process_and_in_process_fallback_give_the_same_sources(idle):
    """The worker process runs the same fit as the fallback thread: identical sources; it
    runs in a session of its own. Both yield to the reader: with ``idle`` (a driver on
    cores of its own) the resolver's thread and worker run as SCHED_IDLE; otherwise the
    worker is niced and the thread keeps the reader's priority (never starved while it
    holds the interpreter lock)."""
    import threading

    from ae_eval.overlap_trials import simulate_overlaps
    from ae_tactile.pipeline import OverlapResolver

    cfg = SimConfig(reflections=True)
    d = simulate_overlaps(1, cfg, separation_s=np.array([4e-6]), amplitude_ratio=2.0,
                          snr_db=30.0, rng=5)
    view = PacketView(d["samples_v"][0], d["sample_rate_hz"], int(d["onset_index"][0]), 0, 7)
    results = {}
    for use_process in (True, False):
        got, done = [], threading.Event()
        def hand_over(recs, got=got, done=done):
            got.extend(recs)
            done.set()

        r = OverlapResolver(cfg.geometry, hand_over, use_process=use_process, idle=idle)
        if use_process:
            # in a session of its own: a Ctrl-C at the terminal goes to the node only
            assert os.getsid(r._proc.pid) == r._proc.pid != os.getsid(0)
        r.submit([view])
        assert done.wait(300.0), dict(r.counts)
        assert ("overlap_worker_unavailable" in r.counts) is (not use_process)
        # Linux schedules threads one by one: the worker process (it answered) and the
        # resolver's own thread
        if use_process:
            assert _priority(r._proc.pid) == ("idle" if idle else "nice")
        assert _priority(r._thread.native_id) == ("idle" if idle else "same")
        r.close()
        results[use_process] = got
    assert len(results[True]) == len(results[False]) == 2
    for a, b in zip(results[True], results[False]):
        assert a.packet_ids == b.packet_ids == (7,)
        assert np.array_equal(a.point_m, b.point_m) and a.time_ns == b.time_ns


@pytest.mark.parametrize("inline_max", [0, 2])
def test_slip_events_do_not_depend_on_when_the_overlap_resolver_answers(inline_max):
    """The slip detector sees every emission in time order: the windows the overlap
    resolver handles (its worker process answers milliseconds later, while the following
    packets are already localized; or, with ``overlap_inline_max``, the reader at once) give
    the same slip events as resolving them on the spot, in the same order with the same
    stamps. (Processed late, after newer ones, the emissions of the scene's overlapping
    windows made a SLIP ~0.35 s before gross slip.)"""
    from ae_tactile.localization.overlap import resolve_overlaps
    from ae_tactile.pipeline import source_record

    views, sc, _ = _slip_scene_packets()
    geo = sc.config.geometry

    # reference: each overlapping window resolved at once, events in time order
    loc = PacketLocalizer("ml", geometry=geo)
    stage = SlipStage(SlipConfig())
    expected = []
    for v in views:
        recs = loc.process([v])
        for p in loc.overlap_windows:
            res = resolve_overlaps(
                np.asarray(p.samples_v, float)[None], p.sample_rate_hz, [p.onset_index],
                geometry=geo,
            )[0]
            if res.accepted:
                recs += [source_record(p, src) for src in res.sources]
        loc.overlap_windows = []
        expected += stage.process(sorted(recs, key=lambda r: r.time_ns))
    assert any(s.event_type == EventType.SLIP for s in expected)

    # live: the resolver's worker answers while later packets keep coming
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=geo), SlipStage(SlipConfig()))
    pipe.overlap_hold_max_s = 600.0  # however slow the machine, wait for every answer
    pipe.overlap_inline_max = inline_max
    pipe.start_overlaps(wait_s=120.0)
    got = []
    try:
        for v in views:
            pipe.process([v], None, got.extend, on_contacts=got.extend)
        assert pipe.wait_idle(120.0)
        counts = pipe.all_counts()
        assert counts["overlap_windows_resolved"] >= 2  # the scene's overlaps went there
        assert counts["overlap_answered_in_reader"] == (counts["overlap_windows_resolved"]
                                                        if inline_max else 0)
        assert "slip_hold_expired" not in counts
    finally:
        pipe.close()
    # a contact's begin / end and its slip events, each in the same order with the same stamps
    for kinds in ((EventType.TOUCH, EventType.DETOUCH),
                  (EventType.SLIP_PRECURSOR, EventType.SLIP, EventType.TEXTURE)):
        key = [(int(s.event_type), s.packet_ids, s.time_ns, s.contact_id) for s in expected
               if s.event_type in kinds]
        assert [(int(s.event_type), s.packet_ids, s.time_ns, s.contact_id) for s in got
                if s.event_type in kinds] == key


def test_an_emission_in_the_windows_of_two_triggers_is_handed_out_once():
    """Random touches and releases at 1,000 emissions/s as the fingertip renders them: every
    emission triggers a window of its own, so two emissions microseconds apart lie in both
    windows and the overlap resolver finds both in each. Each true emission must reach the
    hand at most once (the second find is dropped and counted), and none is lost for it,
    nor for sending the second window of a pair to the worker instead of the reader."""
    from ae_tactile.pipeline import COVERED_TOL_S
    from ae_tactile.sim.scene import load_scene

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sc = load_scene(
        os.path.join(root, "config", "scenes", "random_touches.yaml"),
        {"duration_s": 3.0, "params": {"rate_hz": 500.0}},
    )
    src = sc.triggered_source(pretrigger_s=8e-6, window_s=40e-6)
    b = src.next_packets(1 << 20)
    fs = b.sample_rate_hz
    views = [
        PacketView(b.samples_v[i], fs, int(b.onset_index[i]),
                   int(round(b.start_index[i] * 1e9 / fs)), i)
        for i in range(len(b))
    ]
    truth_ns = np.asarray(b.emissions.time_ns, dtype=np.int64)

    def run(inline_max, covered_tol_s=COVERED_TOL_S):
        got = []
        pipe = ContactPipeline(PacketLocalizer("ml", geometry=sc.config.geometry), None)
        pipe.overlap_inline_max = inline_max
        pipe.overlap_covered_tol_s = covered_tol_s
        pipe.start_overlaps(wait_s=120.0)
        try:
            for i in range(0, len(views), 8):
                pipe.process(views[i : i + 8], got.extend)
            assert pipe.wait_idle(300.0)
            counts = pipe.all_counts()
        finally:
            pipe.close()
        # which true emission each event is (nearest emission instant; all within 1 us)
        t = np.array([e.time_ns for e in got], dtype=np.int64)
        j = np.clip(np.searchsorted(truth_ns, t), 1, len(truth_ns) - 1)
        j = np.where(np.abs(truth_ns[j - 1] - t) < np.abs(truth_ns[j] - t), j - 1, j)
        assert np.abs(truth_ns[j] - t).max() < 1000
        err = np.linalg.norm(np.array([e.point_m for e in got]) - b.emissions.point_m[j], axis=1)
        assert np.percentile(err, 99) < 0.5e-3
        ids, n = np.unique(j, return_counts=True)
        assert n.max() == 1, [(int(i), int(k)) for i, k in zip(ids, n) if k > 1]
        return set(ids.tolist()), counts

    found, counts = run(0)  # every window with the worker (the default)
    # the scene has such emissions, and the resolver found them in both windows
    pair = np.flatnonzero(np.diff(truth_ns) < 3000)  # < 3 us apart: in each other's window
    assert pair.size >= 3 and counts["overlap_duplicates"] >= 1, dict(counts)
    # both of such a pair reach the hand where the resolver accepted their window
    assert counts["overlap_windows_resolved"] >= 2
    # quick answers in the reader: the second window of a pair goes to the worker, and
    # that loses nothing (answering every window on its own finds the same emissions)
    found_inline, counts_inline = run(2)
    assert counts_inline["overlap_covered"] >= 1
    assert counts_inline["overlap_answered_in_reader"] >= 1
    found_alone, counts_alone = run(2, 0.0)
    assert found == found_inline == found_alone, (
        found ^ found_inline, found ^ found_alone, dict(counts_inline), dict(counts_alone)
    )


def test_a_pair_window_sent_to_the_worker_repeats_nothing_the_reader_handed_out():
    """With quick answers in the reader: a window triggered where a window just answered
    there was (the second window of a pair holds the same emissions) goes to the worker,
    whose answer repeats those emissions: they are dropped, also when a later window of
    the same batch, milliseconds newer, was answered in the reader meanwhile."""
    from ae_eval.overlap_trials import simulate_overlaps

    cfg = SimConfig(reflections=True)
    d = simulate_overlaps(2, cfg, separation_s=np.array([4e-6, 5e-6]), amplitude_ratio=1.0,
                          snr_db=30.0, rng=4)

    def view(i, stamp_ns, seq):
        return PacketView(d["samples_v"][i], d["sample_rate_hz"], int(d["onset_index"][i]),
                          stamp_ns, seq)

    a, c = view(0, 10**9, 1), view(1, 10**9 + 5 * 10**6, 3)  # 5 ms apart
    a2 = view(0, 10**9, 2)  # the pair's second window: the same trigger and emissions
    got = []
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), None)
    pipe.overlap_inline_max = 2
    try:
        pipe.process([a, a2, c], got.extend)
        assert pipe.wait_idle(300.0)
        counts = pipe.all_counts()
    finally:
        pipe.close()
    assert counts["overlap_answered_in_reader"] == 2 and counts["overlap_covered"] == 1
    assert counts["overlap_windows_resolved"] == 3, dict(counts)  # a2 answered as well
    assert len(got) == 4, [(e.packet_ids, e.time_ns) for e in got]
    assert counts["overlap_duplicates"] == 2
    for i, seq in ((0, 1), (1, 3)):  # each true emission once, from its own window
        pts = np.array([e.point_m for e in got if e.packet_ids == (seq,)])
        err = np.linalg.norm(pts[:, None, :] - d["points_m"][i][None], axis=2).min(axis=0)
        assert len(pts) == 2 and err.max() < 0.1e-3


@functools.lru_cache(maxsize=1)
def _a_hard_window():
    """The first window of random touches (500 emissions/s) that the pipeline hands to the
    overlap resolver and whose quick answer is DEFERRED: (view, samples, geometry, the
    exhaustive search's answer)."""
    from ae_tactile.localization.overlap import resolve_overlaps
    from ae_tactile.sim.scene import load_scene

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sc = load_scene(
        os.path.join(root, "config", "scenes", "random_touches.yaml"),
        {"duration_s": 3.0, "params": {"rate_hz": 500.0}},
    )
    geo = sc.config.geometry
    b = sc.triggered_source(pretrigger_s=8e-6, window_s=40e-6).next_packets(1 << 20)
    fs = b.sample_rate_hz
    loc = PacketLocalizer("ml", geometry=geo)
    view = None
    for i in range(len(b)):
        v = PacketView(b.samples_v[i], fs, int(b.onset_index[i]), 10**9, i)
        loc.process([v])  # a window the pipeline hands to the overlap resolver ...
        x = b.samples_v[i].astype(np.float64)[None]
        if loc.overlap_windows and resolve_overlaps(
            x, fs, [v.onset_index], geometry=geo, exhaustive=False
        )[0].reason == 10:  # ... whose quick answer is DEFERRED
            view, hard = v, i
            break
    assert view is not None, "the scene has a hard overlapping window"
    full = resolve_overlaps(b.samples_v[hard].astype(np.float64)[None], fs,
                            [int(b.onset_index[hard])], geometry=geo)[0]
    return view, b.samples_v[hard], geo, full


def test_a_window_deferred_in_the_reader_gets_the_exhaustive_answer_of_the_worker():
    """With quick answers in the reader, a hard window (the quick search's first joint fit
    leaves more than noise: DEFERRED) goes to the worker for the exhaustive search alone;
    its events are those of the exhaustive search run directly."""
    from ae_tactile.pipeline import source_record

    view, _, geo, full = _a_hard_window()
    expected = [source_record(view, s) for s in full.sources] if full.accepted else []
    got = []
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=geo), SlipStage(SlipConfig()))
    pipe.overlap_inline_max = 2
    try:
        pipe.process([view], got.extend)
        assert pipe.wait_idle(300.0)
        counts = pipe.all_counts()
    finally:
        pipe.close()
    assert counts["overlap_deferred"] == 1 and "overlap_answered_in_reader" not in counts
    assert [(e.time_ns, e.point_m) for e in got] == [(e.time_ns, e.point_m) for e in expected]
    answered = counts["overlap_windows_resolved"] + sum(
        v for k, v in counts.items() if k.startswith("overlap_rejected_")
    )
    assert answered == 1  # the worker answered it once, with the exhaustive search only
    assert counts["overlap_worker_answers"] == 1 and "overlap_quick_in_thread" not in counts


def test_the_pair_window_of_a_deferred_window_is_answered_by_the_worker_alone():
    """The second window of a pair whose first window was DEFERRED in the reader is likely
    hard too: the worker process gives both its answers (quick, then exhaustive), and the
    resolver's thread fits nothing beside the reader. Each emission reaches the hand once:
    those of the exhaustive search of the first window."""
    from ae_tactile.pipeline import source_record

    view, samples, geo, full = _a_hard_window()
    pair = PacketView(samples, view.sample_rate_hz, view.onset_index, view.stamp_ns, 99)
    expected = [source_record(view, s) for s in full.sources] if full.accepted else []
    got = []
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=geo), SlipStage(SlipConfig()))
    pipe.overlap_inline_max = 2
    try:
        pipe.process([view, pair], got.extend)
        assert pipe.wait_idle(300.0)
        counts = pipe.all_counts()
    finally:
        pipe.close()
    assert counts["overlap_covered"] == 1 and "overlap_quick_in_thread" not in counts
    # the first window: the exhaustive answer; its pair: the quick one (DEFERRED) and the
    # exhaustive one, whose emissions repeat the first window's
    assert counts["overlap_worker_answers"] == 3 and counts["overlap_deferred"] == 2
    assert counts["overlap_duplicates"] == len(expected)
    assert [(e.time_ns, e.point_m) for e in got] == [(e.time_ns, e.point_m) for e in expected]


def test_a_batchs_touch_goes_out_before_a_later_window_of_the_batch_is_fitted():
    """A batch holding a packet and, 5 ms later, an overlapping window fitted in the reader
    (about a millisecond): the packet's slip step runs first, so its TOUCH is handed out
    before the window's emissions are localized; the slip stage then takes the window's
    two emissions too, none out of order."""
    from ae_eval.overlap_trials import simulate_overlaps

    views, _, _ = _packets(n=1)
    first = views[0]  # stamp 1 s
    cfg = SimConfig(reflections=True)
    d = simulate_overlaps(1, cfg, separation_s=np.array([4e-6]), amplitude_ratio=1.0,
                          snr_db=30.0, rng=4)
    window = PacketView(d["samples_v"][0], d["sample_rate_hz"], int(d["onset_index"][0]),
                        first.stamp_ns + 5_000_000, 7)  # 5 ms later
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), SlipStage(SlipConfig()))
    pipe.overlap_inline_max = 2
    seq = []  # what was handed out, in order

    try:
        pipe.process([first, window], lambda rs: seq.extend(("localized", r.packet_ids)
                                                            for r in rs),
                     on_contacts=lambda rs: seq.extend((EventType(r.event_type).name,
                                                        r.packet_ids) for r in rs))
        assert pipe.wait_idle(300.0)
        counts, slip_counts = pipe.all_counts(), pipe.slip.all_counts()
    finally:
        pipe.close()
    assert counts["overlap_answered_in_reader"] == 1
    assert seq[:2] == [("localized", (0,)), ("TOUCH", (0,))], seq  # before the fit
    assert [s for s in seq if s[0] == "localized"][1:] == [("localized", (7,))] * 2, seq
    assert slip_counts["contacts_in"] == 3 and slip_counts["slip_rejected_out_of_order"] == 0


def _pairs_and_their_quick_events(n, rng):
    """n two-emission windows (4 us apart, 30 dB) as packets 1 s apart, and the sorted
    (stamp, point) of the emissions their quick answers hold (all accepted: none DEFERRED)."""
    from ae_eval.overlap_trials import simulate_overlaps
    from ae_tactile.localization.overlap import resolve_overlaps
    from ae_tactile.pipeline import source_record

    cfg = SimConfig(reflections=True)
    d = simulate_overlaps(n, cfg, separation_s=4e-6, amplitude_ratio=1.5, snr_db=30.0, rng=rng)
    fs = d["sample_rate_hz"]
    views = [PacketView(d["samples_v"][i], fs, int(d["onset_index"][i]), 10**9 * (i + 1), i)
             for i in range(n)]
    quick = [resolve_overlaps(d["samples_v"][i][None], fs, [v.onset_index],
                              geometry=cfg.geometry, exhaustive=False)[0]
             for i, v in enumerate(views)]
    assert all(q.accepted and len(q.sources) == 2 for q in quick)
    expected = sorted((r.time_ns, tuple(r.point_m)) for v, q in zip(views, quick)
                      for r in (source_record(v, s) for s in q.sources))
    return cfg, views, expected


def _beside_the_reader(cfg, views, before=None):
    """Play the packets one by one through a pipeline with overlap_inline_max 0 (its
    resolver started first; then ``before()``), wait until it is idle: (events, counts)."""
    got = []
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), SlipStage(SlipConfig()))
    pipe.overlap_inline_max = 0
    try:
        pipe.start_overlaps(wait_s=120.0)
        if before is not None:
            before()
        for v in views:
            pipe.process([v], got.extend)
        assert pipe.wait_idle(300.0)
        return got, pipe.all_counts()
    finally:
        pipe.close()


def test_overlapping_windows_beside_the_reader_get_the_quick_answer_in_the_resolver_thread():
    """overlap_inline_max 0: every overlapping window goes to the resolver; with numba its
    thread computes the quick answer itself (no worker process round trip) and hands out
    exactly the quick answer's emissions; only DEFERRED windows reach the worker."""
    from ae_tactile.localization import overlap

    cfg, views, expected = _pairs_and_their_quick_events(4, rng=3)
    got, counts = _beside_the_reader(cfg, views)
    assert sorted((e.time_ns, tuple(e.point_m)) for e in got) == expected
    assert "overlap_answered_in_reader" not in counts
    if overlap._kernels.NUMBA_AVAILABLE:
        assert counts["overlap_quick_in_thread"] == 4
        assert "overlap_worker_answers" not in counts
    else:  # the worker process computes the quick answers
        assert counts["overlap_worker_answers"] == 4


def test_a_quick_fit_that_fails_in_the_resolver_thread_is_answered_by_the_worker(monkeypatch):
    """A failure of the quick fit in the resolver's thread (injected here: this process's
    resolve_overlaps raises; the worker process runs the real one) loses no window: it is
    counted and the worker process answers it, with the same emissions."""
    from ae_tactile.localization import overlap

    if not overlap._kernels.NUMBA_AVAILABLE:
        pytest.skip("numba absent: the quick fit runs in the worker process anyway")
    cfg, views, expected = _pairs_and_their_quick_events(2, rng=5)

    def broken(*args, **kwargs):
        raise RuntimeError("injected failure of the in-process fit")

    got, counts = _beside_the_reader(
        cfg, views, before=lambda: monkeypatch.setattr(overlap, "resolve_overlaps", broken)
    )
    assert counts["overlap_errors"] == 2 and counts["overlap_worker_answers"] == 2
    assert "overlap_quick_in_thread" not in counts
    assert sorted((e.time_ns, tuple(e.point_m)) for e in got) == expected


def test_duplicate_check_survives_stamps_that_go_back_while_windows_are_pending():
    """A device reset moves the stamps back while overlapping windows are still with the
    resolver: the events of the new stamps are handed out (none lost, no error), and the
    windows' answers still come."""
    import threading

    from ae_eval.overlap_trials import simulate_overlaps

    cfg = SimConfig(reflections=True)
    d = simulate_overlaps(1, cfg, separation_s=np.array([4e-6]), amplitude_ratio=1.0,
                          snr_db=30.0, rng=3)
    n_win = 20  # the resolver's work for a while (milliseconds each), at 50 s + k ms
    windows = [
        PacketView(d["samples_v"][0], d["sample_rate_hz"], int(d["onset_index"][0]),
                   50 * 10**9 + k * 10**6, 900 + k)
        for k in range(n_win)
    ]
    views, truth, _ = _packets(n=6, seed=8)  # stamped from 1 s: 49 s before the windows
    got, done = [], threading.Event()

    def on_contacts(recs):
        got.extend(recs)
        if sum(r.packet_ids[0] >= 900 for r in got) >= 2 * n_win:
            done.set()

    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), None)
    pipe.localizer.warm_up()
    pipe.start_overlaps(wait_s=120.0)
    try:
        pipe.process(windows, on_contacts)
        pipe.process(views, on_contacts)  # at once, while the windows are with the resolver
        assert done.wait(300.0), dict(pipe.all_counts())
    finally:
        pipe.close()
    assert sorted(r.packet_ids[0] for r in got if r.packet_ids[0] < 900) == list(range(6))
    assert sum(r.packet_ids[0] >= 900 for r in got) == 2 * n_win
    assert "overlap_errors" not in pipe.all_counts()
