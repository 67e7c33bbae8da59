# SPDX-License-Identifier: Apache-2.0
"""Per-packet input checks on the raw samples (issue 37 points 3 and 5): four identical
channels are a rejection in every public call, and a packet clipped at a rail is saturated
whatever the device's flag says. Packets from the simulator on zoo devices (not only the
nominal one); the expectations are physical (four sensors add independent noise; a clipped
channel holds its rail), not measured rates."""

import math

import numpy as np
import pytest

from ae_eval.zoo import ZOO, held_out
from ae_tactile.dsp.channel_checks import identical_channels, packet_clipped, packet_identical
from ae_tactile.localization import Localizer, Reason, localize
from ae_tactile.pipeline import ContactPipeline, PacketLocalizer
from ae_tactile.records import PacketView
from ae_tactile.sim import render_triggered

DEVICES = [ZOO["nominal"], ZOO["rc2_bessel6"], ZOO["textbook"], ZOO["alpha_1e6"],
           *held_out(5, 2)]


def _packets(dev, n, seed, max_polar_deg=40.0, min_polar_deg=0.0, fs=10e6, snr_db=30.0):
    cfg = dev.config("water_skin", fs)
    g = np.random.default_rng(seed)
    c = g.uniform(math.cos(math.radians(max_polar_deg)), math.cos(math.radians(min_polar_deg)),
                  n)
    pts = cfg.geometry.surface_point_from_angles(np.arccos(c), g.uniform(0, 2 * math.pi, n))
    return cfg, render_triggered(pts, cfg, snr_db=snr_db, rng=g)


def _copies(pk):
    """One channel (a real touch's channel 0, with its noise) on all four inputs."""
    return np.repeat(pk.samples_v[:, :1], 4, axis=1)


@pytest.mark.parametrize("dev", DEVICES, ids=lambda d: d.name)
def test_identical_channels_are_told_from_four_sensors_on_every_device(dev):
    cfg, pk = _packets(dev, 40, 1, max_polar_deg=3.0)  # apex touches: nearly one waveform
    assert not identical_channels(pk.samples_v, pk.onset_index).any()
    assert identical_channels(_copies(pk), pk.onset_index).all()
    # without a pretrigger the ADC's quantization (or the given noise) is the yardstick
    assert identical_channels(_copies(pk)).all()
    assert not identical_channels(pk.samples_v, None, pk.noise_rms_v).any()


@pytest.mark.parametrize("dev", DEVICES, ids=lambda d: d.name)
def test_identical_channels_are_rejected_by_localize_and_localize_one(dev):
    cfg, pk = _packets(dev, 12, 2, 30.0, 10.0)
    fs = cfg.sample_rate_hz
    x = _copies(pk)
    for engine in (None, "numpy"):
        res = localize(x, fs, pk.onset_index, geometry=cfg.geometry, engine=engine)
        assert not res.accepted.any()
        assert (res.reason == Reason.NO_SIGNAL).all()
        assert (res.confidence == 0).all()
        assert localize(pk.samples_v, fs, pk.onset_index, geometry=cfg.geometry,
                        engine=engine).accepted.mean() > 0.8
    one = Localizer("ml")
    for i in range(len(x)):
        r = one.localize_one(x[i], fs, int(pk.onset_index[i]), geometry=cfg.geometry)
        assert not r.accepted and r.reason == Reason.NO_SIGNAL and r.confidence == 0.0
    ok = [one.localize_one(pk.samples_v[i], fs, int(pk.onset_index[i]),
                           geometry=cfg.geometry).accepted for i in range(len(x))]
    assert np.mean(ok) > 0.8


@pytest.mark.parametrize("batch", [1, 10])
def test_identical_channels_are_rejected_and_counted_by_the_pipeline(batch):
    cfg, pk = _packets(ZOO["rc2_bessel6"], 20, 3, 30.0, 10.0)
    x = _copies(pk)
    pipe = ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), None)
    views = [PacketView(x[i], cfg.sample_rate_hz, int(pk.onset_index[i]), 10**9 * (i + 1), i)
             for i in range(len(x))]
    out = []
    for k in range(0, len(views), batch):
        pipe.process(views[k : k + batch], out.extend)
    assert out == []
    assert pipe.localizer.counts["rejected_IDENTICAL_CHANNELS"] == len(x)


def _clip_half(x, ch=0):
    """Channel ``ch`` of each packet clipped at half its peak (an amplifier's rail)."""
    y = x.copy()
    for i in range(len(y)):
        lim = 0.5 * np.abs(y[i, ch]).max()
        y[i, ch] = np.clip(y[i, ch], -lim, lim)
    return y


@pytest.mark.parametrize("dev", DEVICES, ids=lambda d: d.name)
def test_a_flat_top_is_found_from_the_samples(dev):
    cfg, pk = _packets(dev, 40, 4, snr_db=40.0)
    fs = cfg.sample_rate_hz
    assert not any(packet_clipped(w, fs) for w in pk.samples_v)
    assert all(packet_clipped(w, fs) for w in _clip_half(pk.samples_v))
    # a rail below zero (the channel's negative extreme held)
    y = pk.samples_v.copy()
    for i in range(len(y)):
        lo = 0.5 * y[i, 2].min()
        y[i, 2] = np.maximum(y[i, 2], lo)
    dominant_negative = [abs(w[2].min()) > w[2].max() for w in pk.samples_v]
    assert all(packet_clipped(w, fs) for w, d in zip(y, dominant_negative) if d)


def test_a_clipped_packet_without_the_flag_is_saturated_and_counted_by_the_pipeline():
    cfg, pk = _packets(ZOO["nominal"], 10, 5, snr_db=40.0)
    x = _clip_half(pk.samples_v)
    loc = PacketLocalizer("ml", geometry=cfg.geometry)
    for batch in (1, 10):
        views = [PacketView(x[i], cfg.sample_rate_hz, int(pk.onset_index[i]),
                            10**9 * (i + 1), i, saturated=False) for i in range(len(x))]
        out = []
        for k in range(0, len(views), batch):
            out += loc.process(views[k : k + batch])
        assert out == []
    assert loc.counts["clipped_from_samples"] == 2 * len(x)
    assert loc.counts["rejected_SATURATED"] == 2 * len(x)
    # the same packets unclipped are localized
    clean = [PacketView(pk.samples_v[i], cfg.sample_rate_hz, int(pk.onset_index[i]),
                        10**9 * (i + 1), i) for i in range(len(x))]
    assert len(PacketLocalizer("ml", geometry=cfg.geometry).process(clean)) >= 8


def test_packet_identical_checks_its_input():
    with pytest.raises(ValueError):
        packet_identical(np.zeros((3, 10)))
    assert not packet_identical(np.zeros((4, 10)))  # no signal: another check's rejection
    assert not packet_identical(np.full((4, 10), np.nan))
