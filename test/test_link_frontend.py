# SPDX-License-Identifier: Apache-2.0
"""The link's per-packet front end: int16 counts -> float32 volts, pre-trigger noise RMS
and onset index. The compiled kernel against the numpy reference (same volts bit for bit,
same onset, same noise to rounding), and both against what was put into the window (a
known noise level, a known arrival). No timing here (bench/)."""

import numpy as np
import pytest

from ae_tactile.jit import NUMBA_AVAILABLE
from ae_tactile.link import packet_volts_noise_onset, window_noise_and_onset
from ae_tactile.sim import SimConfig, render_triggered

needs_numba = pytest.mark.skipif(not NUMBA_AVAILABLE, reason="numba not importable here")
VPC = 3.0517578125e-05  # 2 V full scale at 16 bits


def reference(counts, vpc, pre):
    volts = (counts * np.float32(vpc)).astype(np.float32)
    return (volts,) + window_noise_and_onset(volts, pre)


def simulated_counts(rng, fs, snr_db, n=60):
    cfg = SimConfig().replace(sample_rate_hz=fs)
    g = cfg.geometry
    ct = rng.uniform(np.cos(np.deg2rad(70)), 1, n)
    pts = g.surface_point_from_angles(np.arccos(ct), rng.uniform(0, 2 * np.pi, n))
    pk = render_triggered(pts, cfg, snr_db=snr_db, rng=rng)
    scale = 0.5 / np.abs(pk.samples_v).max()  # half of full scale at most
    return np.rint(pk.samples_v * scale / VPC).astype(np.int16)


@needs_numba
@pytest.mark.parametrize("fs, snr_db", [(10e6, 40.0), (10e6, 10.0), (2e6, 20.0)])
def test_compiled_front_end_agrees_with_the_numpy_reference(fs, snr_db):
    rng = np.random.default_rng(int(fs) + int(snr_db))
    counts = simulated_counts(rng, fs, snr_db)
    for pre in (80, 40, 3, 0, counts.shape[2] - 1, counts.shape[2] + 7, -5):
        for c in counts:
            c = c.copy()
            c.flags.writeable = bool(pre % 2)  # read-only, as decoded from the wire, and not
            v, noise, onset = packet_volts_noise_onset(c, VPC, pre)
            rv, rnoise, ronset = reference(c, VPC, pre)
            assert v.dtype == np.float32 and np.array_equal(v, rv)
            assert onset == ronset
            assert noise == pytest.approx(rnoise, rel=1e-12, abs=0.0)


@needs_numba
def test_constant_and_extreme_windows_agree():
    flat = np.full((4, 400), 1234, dtype=np.int16)  # no noise: the onset is the trigger
    rails = np.tile(np.array([32767, -32768], dtype=np.int16), (4, 200))
    for c in (flat, rails):
        v, noise, onset = packet_volts_noise_onset(c, VPC, 80)
        rv, rnoise, ronset = reference(c, VPC, 80)
        assert np.array_equal(v, rv) and onset == ronset and noise == pytest.approx(rnoise)
    assert packet_volts_noise_onset(flat, VPC, 80)[1:] == (0.0, 80)


@pytest.mark.parametrize("path", [pytest.param("compiled", marks=needs_numba), "numpy"])
def test_noise_and_onset_find_what_was_put_in(path):
    """Gaussian noise of known sigma, then a step of 10 sigma at a known sample."""
    rng = np.random.default_rng(7)
    sigma_counts, arrival, pre = 40.0, 230, 200
    hits = 0
    for k in range(50):
        x = rng.normal(0.0, sigma_counts, (4, 400)) + 500.0  # with a DC offset
        x[k % 4, arrival:] += 10.0 * sigma_counts * (1 - 2 * (k % 2))
        c = np.rint(x).astype(np.int16)
        if path == "compiled":
            _, noise, onset = packet_volts_noise_onset(c, VPC, pre)
        else:
            _, noise, onset = reference(c, VPC, pre)
        assert noise == pytest.approx(sigma_counts * VPC, rel=0.12)
        # 4-sigma crossings of the noise before the step (p ~ 2.5e-4 per sample x 4 ch)
        assert pre // 2 <= onset <= arrival
        hits += onset == arrival
    assert hits >= 45
