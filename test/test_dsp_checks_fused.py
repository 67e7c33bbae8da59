# SPDX-License-Identifier: Apache-2.0
"""`packet_checks` (the pipeline's per-packet check in one compiled call) answers what its
reference, `packet_identical` then `packet_clipped`, answers: on random packets and on the
hard ones (four copies of one channel, with an offset, quantized; flat tops at a rail,
short of the run, a few LSB high; NaN; no onset in the window; other dtypes)."""

from __future__ import annotations

import numpy as np
import pytest

from ae_tactile.dsp.channel_checks import (
    CHECK_CLIPPED,
    CHECK_IDENTICAL,
    CHECK_PASSED,
    packet_checks,
    packet_clipped,
    packet_identical,
)


def reference(x, onset, nv, fs, flagged) -> int:
    """The two public tests in the pipeline's order."""
    if packet_identical(x, onset, nv):
        return CHECK_IDENTICAL
    if not flagged and packet_clipped(x, fs):
        return CHECK_CLIPPED
    return CHECK_PASSED


def packets(rng):
    """(window, onset, noise sigma) of random and hard packets."""
    m = int(rng.choice([16, 64, 400]))
    lsb = 2.0**-11
    t = np.arange(m)
    burst = np.sin(2 * np.pi * 0.07 * t) * np.exp(-((t - m / 2) / (m / 6)) ** 2)
    noise = rng.normal(0.0, 1.0, (4, m))
    kind = int(rng.integers(9))
    amp = float(rng.choice([0.01, 1.0, 40.0]))
    if kind == 0:  # four sensors' view: own noise
        x = amp * burst + noise
    elif kind == 1:  # one signal copied onto four inputs
        x = np.repeat((amp * burst + noise[0])[None], 4, axis=0)
    elif kind == 2:  # copied, with ADC offsets
        x = np.repeat((amp * burst)[None], 4, axis=0) + rng.integers(-3, 4, (4, 1))
    elif kind == 3:  # copied, quantized, noise-free
        x = np.repeat(np.rint(amp * 50 * burst)[None], 4, axis=0)
    elif kind == 4:  # flat top at a rail
        x = np.clip(amp * 30 * burst + noise, -20, 20)
    elif kind == 5:  # a smooth peak a few LSB high
        x = np.rint(3 * burst + 0.2 * noise)
    elif kind == 6:  # NaN
        x = amp * burst + noise
        x[int(rng.integers(4)), int(rng.integers(m))] = np.nan
    elif kind == 7:  # all zero
        x = np.zeros((4, m))
    else:  # a short run at the extreme
        x = np.rint(amp * burst * 100 + noise)
        x[:, m // 2 : m // 2 + 3] = x.max()
    x = x * lsb
    onset = int(rng.choice([0, 1, 9, m // 4, m - 1, m, -1]))
    nv = float(rng.choice([0.0, lsb, np.nan, -1.0]))
    return x, onset, nv


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
def test_fused_check_answers_as_its_two_reference_tests(dtype):
    rng = np.random.default_rng(41)
    seen = set()
    for _ in range(600):
        x, onset, nv = packets(rng)
        if dtype is np.int16:
            if not np.isfinite(x).all():
                continue  # ADC counts carry no NaN
            x = np.rint(x * 2**11)
        x = x.astype(dtype)
        fs = float(rng.choice([1e6, 10e6, 40e6]))
        for flagged in (False, True):
            want = reference(x, onset, nv, fs, flagged)
            assert packet_checks(x, onset, nv, fs, flagged) == want
            seen.add(want)
    assert seen == {CHECK_PASSED, CHECK_IDENTICAL, CHECK_CLIPPED}  # every answer exercised


def test_a_bad_shape_raises_as_packet_identical_does():
    with pytest.raises(ValueError):
        packet_checks(np.zeros((3, 16)), 4, 0.0, 1e7, False)
