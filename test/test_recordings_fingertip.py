# SPDX-License-Identifier: Apache-2.0
"""Fingertip recordings the tests write from the simulator's stream (a WAV and an NPY):
hit onsets on the known arrivals, every emission replayed through the live device's
`ContactPipeline` to a contact event at the scene's point and time, the incipient-slip
scene's slip events as the virtual device's packets give them, a channel map, the
command line, and the errors of a recording that is no fingertip."""

import os

import numpy as np
import pytest
from scipy.io import wavfile

from ae_tactile.pipeline import ContactPipeline, PacketLocalizer, PacketView, SlipStage
from ae_tactile.recordings import RecordingError, detect
from ae_tactile.recordings.cli import main as cli_main
from ae_tactile.records import EventType
from ae_tactile.sim import EmissionList, SimConfig, StreamRenderer
from ae_tactile.sim.scene import load_scene
from ae_tactile.slip import SlipConfig

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOISE_V = 2e-3  # about 30 dB SNR for these touches
FLOATING_DB = 15.0  # threshold 5.6 x the noise rms


@pytest.fixture(scope="module")
def touches(tmp_path_factory):
    """Eight touches and releases 2 ms apart, the first 30 us into the file, rendered
    as the device's stream and written as a float WAV and an NPY (N, 4)."""
    cfg = SimConfig()
    geo = cfg.geometry
    rng = np.random.default_rng(1)
    n = 8
    xy = rng.uniform(-6e-3, 6e-3, (n, 2))
    pts = geo.surface_point_from_xy(xy[:, 0], xy[:, 1])
    t_ns = (np.arange(n) * 2_000_000 + 30_000).astype(np.int64)
    pol = np.where(np.arange(n) % 2, -1, 1)
    em = EmissionList.create(t_ns, pts, "touch", polarity=pol, speed_m_s=0.3,
                             curvature_1_m=1000.0, alpha_1_s=3000.0,
                             density_kg_m3=cfg.density, event_id=np.arange(n))
    x, clipped = StreamRenderer(cfg, noise_rms_v=NOISE_V, seed=3).render(
        em, 0, int(17e-3 * cfg.sample_rate_hz))
    assert not clipped
    d = tmp_path_factory.mktemp("fingertip")
    wavfile.write(d / "tip.wav", int(cfg.sample_rate_hz), x.T.astype(np.float32))
    np.save(d / "tip.npy", x.T)
    return {"dir": d, "cfg": cfg, "points": pts, "t_ns": t_ns, "polarity": pol,
            "arrivals_s": t_ns[:, None] * 1e-9 + geo.arrival_times_s(pts)}


def _match(contacts, t_ns):
    """Index of the emission nearest in time to each event."""
    return [int(np.argmin(np.abs(t_ns - c.time_ns))) for c in contacts]


def test_onsets_of_a_fingertip_wav_sit_on_the_known_arrivals(touches):
    det = detect(touches["dir"] / "tip.wav", floating_db=FLOATING_DB, fingertip=True)
    assert len(det.hits) == 32 and not det.warnings
    fs = touches["cfg"].sample_rate_hz
    err = []
    for h in det.hits:
        k = int(np.argmin(np.abs(touches["arrivals_s"][:, h.channel] - h.onset_time_s)))
        err.append((h.onset_time_s - touches["arrivals_s"][k, h.channel]) * fs)
    assert np.abs(err).max() <= 5.0, err  # samples: the AIC's first high-variance sample
    assert det.hits[0].onset_time_s < 40e-6  # the first emission, 30 us into the file


def test_a_fingertip_wav_replays_to_contact_events_at_the_scene_points(touches):
    det = detect(touches["dir"] / "tip.wav", floating_db=FLOATING_DB, fingertip=True)
    ft = det.fingertip
    assert len(ft.windows) == 8 and len(ft.contacts) == 8
    k = _match(ft.contacts, touches["t_ns"])
    assert sorted(k) == list(range(8))
    pos_err = [np.linalg.norm(np.asarray(c.point_m) - touches["points"][i])
               for c, i in zip(ft.contacts, k)]
    time_err = [abs(c.time_ns - touches["t_ns"][i]) for c, i in zip(ft.contacts, k)]
    assert max(pos_err) < 0.2e-3, pos_err  # [m]
    assert max(time_err) < 1000, time_err  # [ns]
    kinds = [EventType.TOUCH if touches["polarity"][i] > 0 else EventType.DETOUCH for i in k]
    assert [c.event_type for c in ft.contacts] == kinds


def test_a_permuted_npy_with_its_channel_map_gives_the_same_events(touches):
    x = np.load(touches["dir"] / "tip.npy")  # (N, 4)
    perm = (2, 0, 3, 1)  # file row r holds fingertip channel perm[r]
    shuffled = np.empty_like(x)
    shuffled[:, list(range(4))] = x[:, list(perm)]
    np.save(touches["dir"] / "shuffled.npy", shuffled)
    channel_map = [perm.index(k) for k in range(4)]  # fingertip channel k -> file row
    fs = touches["cfg"].sample_rate_hz
    ref = detect(touches["dir"] / "tip.npy", sample_rate_hz=fs, floating_db=FLOATING_DB,
                 fingertip=True).fingertip.contacts
    got = detect(touches["dir"] / "shuffled.npy", sample_rate_hz=fs, floating_db=FLOATING_DB,
                 fingertip=True, channel_map=channel_map).fingertip.contacts
    assert len(got) == len(ref) == 8
    for a, b in zip(ref, got):
        assert a.time_ns == b.time_ns and np.allclose(a.point_m, b.point_m, atol=1e-9)
    wrong = detect(touches["dir"] / "shuffled.npy", sample_rate_hz=fs, floating_db=FLOATING_DB,
                   fingertip=True).fingertip.contacts
    k = _match(wrong, touches["t_ns"])
    assert max(np.linalg.norm(np.asarray(c.point_m) - touches["points"][i])
               for c, i in zip(wrong, k)) > 1e-3  # the map matters


def _triggered_slip(sc):
    """Slip events of the scene's packets as the virtual device cuts them (the live path)."""
    src = sc.triggered_source(pretrigger_s=8e-6, window_s=40e-6)
    views = []
    while len(b := src.next_packets(256)):
        for i in range(len(b)):
            views.append(PacketView(b.samples_v[i], b.sample_rate_hz, int(b.onset_index[i]),
                                    int(round(b.start_index[i] * 1e9 / b.sample_rate_hz)),
                                    len(views)))
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=sc.config.geometry),
                           SlipStage(SlipConfig()))
    slips = []
    for i in range(0, len(views), 4):
        pipe.process(views[i:i + 4], lambda c: None, slips.extend)
    assert pipe.wait_idle(120.0)
    pipe.close()
    return slips


def test_an_incipient_slip_recording_gives_the_live_paths_slip_events(tmp_path):
    """The incipient-slip scene's first 0.12 s, recorded as the device's stream (NPY):
    every emission is a contact event at its point, and the slip precursors come out at
    the times the virtual device's packets give them."""
    path = os.path.join(ROOT, "config", "scenes", "incipient_slip.yaml")
    sc = load_scene(path, {"duration_s": 0.12})
    src, n = sc.streaming_source(), sc.n_samples
    x, truth, pos = np.empty((4, n), np.float32), [], 0
    while pos < n:
        c = src.next_chunk(min(1 << 18, n - pos))
        x[:, pos:pos + c.samples_v.shape[1]] = c.samples_v
        truth.append(c.emissions)
        pos += c.samples_v.shape[1]
    em = EmissionList.concat(truth)
    np.savez(tmp_path / "slip.npz", samples_v=x, sample_rate_hz=sc.config.sample_rate_hz)
    det = detect(tmp_path / "slip.npz", floating_db=FLOATING_DB, fingertip=True,
                 geometry=sc.config.geometry)
    ft = det.fingertip
    assert len(ft.contacts) == len(em) >= 15
    k = _match(ft.contacts, em.time_ns)
    assert sorted(k) == list(range(len(em)))
    err = [np.linalg.norm(np.asarray(c.point_m) - em.point_m[i]) for c, i in zip(ft.contacts, k)]
    assert np.median(err) < 0.3e-3 and max(err) < 1e-3, err
    ours = [(s.event_type, s.time_ns) for s in ft.slip]
    live = [(s.event_type, s.time_ns) for s in _triggered_slip(load_scene(path,
                                                                          {"duration_s": 0.12}))]
    assert len(ours) == len(live) >= 3
    assert all(a[0] == b[0] == EventType.SLIP_PRECURSOR for a, b in zip(ours, live))
    assert max(abs(a[1] - b[1]) for a, b in zip(ours, live)) < 2_000  # [ns]


def test_the_command_line_prints_and_writes_fingertip_events(touches, tmp_path, capsys):
    out = tmp_path / "tip.csv"
    assert cli_main([str(touches["dir"] / "tip.wav"), "--fingertip", "--floating-db", "15",
                     "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "32 hit(s)" in text and "fingertip: 8 window(s) -> 8 contact event(s)" in text
    assert "TOUCH" in text and "DETOUCH" in text
    assert out.read_text().count("\n") == 33
    contacts = (tmp_path / "tip.contacts.csv").read_text().splitlines()
    assert len(contacts) == 9 and contacts[0].startswith("source,time_s,event_type,x_m")
    assert cli_main([str(touches["dir"] / "tip.wav"), "--fingertip", "--channel-map",
                     "0,1,2"]) == 2
    assert "channel map must name 4 different file rows" in capsys.readouterr().err


def test_a_recording_without_four_channels_is_no_fingertip(tmp_path):
    x = np.random.default_rng(0).normal(0, 1e-3, (2, 5000))
    np.save(tmp_path / "two.npy", x)
    with pytest.raises(RecordingError, match="two.npy: 2 channel"):
        detect(tmp_path / "two.npy", sample_rate_hz=1e7, fingertip=True)
