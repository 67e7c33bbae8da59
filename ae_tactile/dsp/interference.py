# SPDX-License-Identifier: Apache-2.0
"""Common-mode electrical interference on packets (a motor driver's switching edges,
ground bounce, ESD spikes): reject it before the localizer, keep real touches.

Electrical interference reaches the four channels at once with one waveform (zero
delays, equal amplitudes), so the localizer puts it at the apex. A touch at or near the
apex also arrives with near-zero delays and nearly equal waveforms, so common mode alone
cannot tell them apart. What does: an acoustic packet has passed the fingertip and the
front end, its spectrum lies inside the front end's band (high-pass f_hp .. low-pass
f_lp); interference coupled after the filters (the ADC lines, the board's ground) keeps
its own spectrum: switching edges and spikes carry energy below f_hp (a step: a DC
offset over the window) and above f_lp (an edge or spike sharper than the anti-alias
filter allows). Per packet (all vectorized over K packets, M samples after the onset):

  s_n      = mean over the 4 channels (the common mode), x_cn the channels
  common   = |s|^2 / mean_c |x_c|^2 (noise power removed): 1 for identical channels
  low      = (mean_n s_n)^2 W / sum s_n^2: share of the window's energy at DC (< 1/W)
  high     = sum (s_{n+1} - s_n)^2 / (2 sum s_n^2 (1 - cos(2 pi f_lp / fs))):
             1 for a tone at f_lp, > 1 only with energy above the front end's band
  score    = common * max(low / low_max, high / high_max)
  shape    = (E - sum_c max_j <x_c, t_j>^2 - N sigma^2) / max((1 - shape_min) E_sig,
             shape_z sqrt(2 N) sigma^2): what the best acoustic template t_j (the front
             end's step response at sub-sample offsets and lags, per channel: near the
             apex the four arrivals differ by a few samples) leaves of the channels' energy
             E over N samples (all four), beyond the noise and the ADC's quantization
             (sigma^2 + LSB^2 / 12), against an acoustic packet's template mismatch or the
             noise's chi^2 spread, whichever is larger (common-mode candidates only;
             score = max(score, common * shape))

The limits and the templates above are the nominal front end's until the device's own
acoustic packets are learnt (``acoustic``: `ae_tactile.dsp.acoustic_model.AcousticLearner`,
from its accepted touches away from the apex): then the spectrum limits are at least what
the device's touches give, and the templates its touches' own waveforms wherever the
nominal ones do not describe them.

Interference when common >= ``common_min`` and score >= 1. Interference shaped by the
front end itself (coupled into the amplifier's input) has an acoustic packet's spectrum
and is not separable from an apex touch by one packet without the wall echo an acoustic
packet brings back at 2R/c (``echo_min``; `echo_ratio` and `EchoLearner` learn it from the
device's own touches), or by the timing of a periodic train (`BurstTrain`): docs/slip.md
gives the measured rates for both couplings.
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.dsp.burst_train import (  # the timing screen, importable from here too
    TRAIN_TOL_S as TRAIN_TOL_S,
)
from ae_tactile.dsp.burst_train import (
    TRAIN_TOL_SAMPLES as TRAIN_TOL_SAMPLES,
)
from ae_tactile.dsp.burst_train import (
    BurstTrain as BurstTrain,
)
from ae_tactile.dsp.templates import (  # the screen's model, importable from here too
    _front_end_lowpass,
    _front_end_templates,
    _lag_templates,
    _pulse_limits,
    _pulses,
)
from ae_tactile.dsp.templates import acoustic_templates as acoustic_templates
from ae_tactile.jit import NUMBA_AVAILABLE, njit

COMMON_MIN = 0.9
LOW_MAX = 0.25
HIGH_MAX = 1.5
SHAPE_MIN = 0.94
SHAPE_LAGS = 10
SHAPE_LEAD = 2
SHAPE_CHUNK = 256  # candidates per shape-test step (memory: 256 x 4 x span floats)
def warm_up(sample_rate_hz: float, highpass_hz=100e3, highpass_order=2, lowpass_hz="auto",
            lowpass_order="auto", *, geometry=None, window_s: float = 20e-6) -> None:
    """Compute the templates a first common-mode packet at this rate would need (the
    defaults of `common_mode_interference`: step responses up to 256 samples, and the shape
    test's templates for the span of a packet whose onset is well inside its window)."""
    lp, order = _front_end_lowpass(sample_rate_hz, lowpass_hz, lowpass_order)
    fs = float(sample_rate_hz)
    for dtype in (np.float32, np.float64):  # the cheap screen's compiled kernel, for
        z = np.zeros((4, 8), dtype)  # writable and read-only arrays (received messages)
        packet_common_share(z, 0.0, 6)
        z.flags.writeable = False
        packet_common_share(z, 0.0, 6)
    front_end = (float(highpass_hz), int(highpass_order), lp, int(order))
    _front_end_templates(fs, 128, front_end)
    t_echo = 10e-6 if geometry is None else 2.0 * geometry.radius_m / geometry.sound_speed_m_s
    n = SHAPE_LEAD + min(int(t_echo * fs) - 1, max(4, int(round(window_s * fs))))
    if n >= SHAPE_LAGS + 4:
        _lag_templates(fs, n, SHAPE_LAGS, front_end)


def _unexplained_share(span, tpls, nv, nv_rel_var, shape_min, shape_z):
    """Shape test of packets ``span`` (K, 4, S): from SHAPE_LEAD samples before the onset to
    the first wall echo. What the best template per channel (rows of ``tpls``: unit-norm
    templates starting 0 .. SHAPE_LAGS - 1 samples into the span) leaves unexplained beyond the
    noise ``nv`` (V^2 per sample, scalar or (K,)), over the larger of the template mismatch
    an acoustic packet may have and shape_z sigma of the noise's chi^2: >= 1 is not an
    acoustic packet."""
    k, _, n = span.shape
    tiny = 1e-30
    # per channel (each its own lag and offset: near the apex the four arrivals differ by
    # up to a few samples, and their mean is no longer one step response); every template
    # runs to the span's end, so a packet's own tail is explained, not counted
    c = span @ tpls.T  # (K, 4, lags x offsets)
    e_span = np.einsum("kcw,kcw->k", span, span)
    resid = e_span - (c * c).max(axis=2).sum(axis=1)
    # the ADC's quantization noise, LSB^2 / 12 (the LSB: the smallest step between the
    # packet's sample values), is part of every packet's residual: added to a given
    # (analog) noise power; the floor of an estimated one (below one LSB of analog noise a
    # pretrigger reads nearly constant)
    steps = np.diff(np.sort(span.reshape(k, -1), axis=1), axis=1)
    lsb = np.where(steps > 0, steps, np.inf).min(axis=1)
    q_v2 = np.where(np.isfinite(lsb), lsb * lsb / 12.0, 0.0)
    nv1 = np.maximum(nv, q_v2) if nv_rel_var > 0.0 else nv + q_v2
    nv1 = np.maximum(nv1, tiny)
    n_dof = 4.0 * (n - 1)  # one amplitude fitted per channel
    excess = resid - n_dof * nv1
    e_sig = np.maximum(e_span - 4.0 * n * nv1, tiny)
    # judged against the larger of the template mismatch an acoustic packet may have
    # ((1 - shape_min) of its energy) and the noise's spread (shape_z sigma of chi^2; an
    # estimated noise power adds its own error, times the dof it is removed from)
    spread = math.sqrt(2.0 * n_dof + n_dof * n_dof * nv_rel_var)
    return excess / np.maximum((1.0 - shape_min) * e_sig, shape_z * spread * nv1)


#: `common_mode_share` removes each channel's mean over the samples before onset - 2 when
#: there are at least this many (an ADC's offset would otherwise count as common mode)
SHARE_MIN_PRETRIGGER = 4


def common_mode_share(windows, noise_rms_v=None, onset_index=None) -> np.ndarray:
    """Common-mode share of each packet's energy (K,): |s|^2 / mean_c |x_c|^2 over the
    window (s the mean of the four channels of ``windows`` (K, 4, M) volts, each channel
    less its mean before ``onset_index`` - 2 where that holds >= SHARE_MIN_PRETRIGGER
    samples; the noise sigma ``noise_rms_v`` (scalar or (K,); None: 0) removed): 1 for one
    waveform on the four channels, 0 where it cannot be told (no energy beyond the noise,
    non-finite). The cheap screen that sends a packet to `common_mode_interference`."""
    x = np.asarray(windows, dtype=np.float64)
    if x.ndim != 3 or x.shape[1] != 4:
        raise ValueError(f"windows must be (K, 4, M), got shape {x.shape}")
    k, _, m = x.shape
    if onset_index is not None:
        npre = np.broadcast_to(np.asarray(onset_index, dtype=np.int64).reshape(-1), (k,)) - 2
        npre = np.clip(npre, 0, m)
        for n in np.unique(npre[npre >= SHARE_MIN_PRETRIGGER]):
            rows = np.flatnonzero(npre == n)
            x[rows] = x[rows] - x[rows, :, : int(n)].mean(axis=2, keepdims=True)
    nv = 0.0 if noise_rms_v is None else np.asarray(noise_rms_v, float).reshape(-1) ** 2
    s = x.mean(axis=1)
    e_s = np.einsum("km,km->k", s, s) - 0.25 * m * nv
    e_ch = np.einsum("kcm,kcm->k", x, x) * 0.25 - m * nv
    with np.errstate(all="ignore"):
        c = np.where(e_ch > 0, e_s / e_ch, 0.0)
    return np.where(np.isfinite(c), c, 0.0)


@njit(cache=True, nogil=True)
def _common_share_kernel(x, nv, npre):  # pragma: no cover - compiled
    """Compiled `common_mode_share` of one packet ``x`` (4, M), noise variance ``nv``,
    channel means over the first ``npre`` samples removed (none when npre < 1)."""
    m = x.shape[1]
    dc = np.zeros(4)
    if npre >= 1:
        for c in range(4):
            acc = 0.0
            for i in range(npre):
                acc += np.float64(x[c, i])
            dc[c] = acc / npre
    e_s = 0.0
    e_ch = 0.0
    for i in range(m):
        a = np.float64(x[0, i]) - dc[0]
        b = np.float64(x[1, i]) - dc[1]
        c = np.float64(x[2, i]) - dc[2]
        d = np.float64(x[3, i]) - dc[3]
        s = a + b + c + d
        e_s += s * s
        e_ch += a * a + b * b + c * c + d * d
    e_s = e_s * 0.0625 - 0.25 * m * nv
    e_ch = e_ch * 0.25 - m * nv
    if not e_ch > 0.0:
        return 0.0
    r = e_s / e_ch
    return r if math.isfinite(r) else 0.0


def packet_common_share(samples_v, noise_rms_v: float = 0.0, onset_index=None) -> float:
    """`common_mode_share` of one packet (4, M) (compiled where numba is, ~1.5 us)."""
    x = samples_v
    if NUMBA_AVAILABLE and isinstance(x, np.ndarray) and x.ndim == 2 and x.shape[0] == 4 and (
        x.dtype == np.float32 or x.dtype == np.float64
    ):
        npre = 0
        if onset_index is not None:
            npre = min(max(int(onset_index) - 2, 0), x.shape[1])
            npre = npre if npre >= SHARE_MIN_PRETRIGGER else 0
        return float(_common_share_kernel(x, float(noise_rms_v) ** 2, npre))
    return float(common_mode_share(np.asarray(x)[None], noise_rms_v, onset_index)[0])


def _noise_power(x, on, noise_rms_v):
    """(noise power per channel [V^2] (scalar or (K,)), its relative variance (0: given),
    whether a noise level is known): given, else from the samples before the onset (the
    trigger's pretrigger) when there are >= 8."""
    if noise_rms_v is not None:
        return np.asarray(noise_rms_v, float).reshape(-1) ** 2, 0.0, True
    npre = int(on.min()) - 2
    if npre >= 8:
        pre = x[:, :, :npre]
        nv = (pre * pre).mean(axis=(1, 2)) - pre.mean(axis=2).__pow__(2).mean(axis=1)
        return nv, 2.0 / (4 * (npre - 1)), True  # chi^2 over 4 (npre - 1) dof
    return 0.0, 0.0, False


def _shape_scores(x, on, cand, common, nv, nv_rel_var, w, fs, geometry, front_end, shape_min,
                  shape_z, learned=None):
    """Shape score of the packets ``cand``: what the best acoustic template per channel
    (sub-sample offsets x lags -SHAPE_LEAD .. SHAPE_LAGS - SHAPE_LEAD - 1 round the onset)
    leaves unexplained, less the noise, against the larger of an acoustic packet's template
    mismatch (1 - shape_min of its energy) and shape_z standard deviations of the noise's
    chi^2 (a weak touch is never rejected for noise), before the first wall echo (2R/c
    after the onset, when the geometry is known). Only with a noise level (given, or from
    >= 8 pretrigger samples): weak touches could not be told from a mismatch."""
    m = x.shape[2]
    t_echo = 10e-6 if geometry is None else 2.0 * geometry.radius_m / geometry.sound_speed_m_s
    nl = SHAPE_LAGS
    nvc = nv if np.size(nv) == 1 else nv[cand]
    st = np.clip(on[cand] - SHAPE_LEAD, 0, None)
    # each packet's span ends before the echo, the analysis length and its window's end
    end = np.minimum(on[cand] + min(int(t_echo * fs) - 1, w), m)
    if learned is not None:  # the device's own waveforms: as long as they are
        end = np.minimum(end, st + learned.span(fs))
    n_span = end - st
    shape_score = np.zeros(cand.size)
    for n in np.unique(n_span[n_span >= nl + 4]):  # shorter: no shape test
        n = int(n)
        tpls = (learned.templates(fs, n, nl) if learned is not None
                else _lag_templates(fs, n, nl, front_end))
        group = np.flatnonzero(n_span == n)
        for i in range(0, group.size, SHAPE_CHUNK):  # bounded memory: (chunk, 4, n)
            part = group[i : i + SHAPE_CHUNK]
            span = x[
                cand[part][:, None, None],
                np.arange(4)[None, :, None],
                (st[part][:, None] + np.arange(n))[:, None, :],
            ]
            shape_score[part] = common[cand[part]] * _unexplained_share(
                span, tpls, nvc if np.size(nvc) == 1 else nvc[part], nv_rel_var,
                shape_min, shape_z,
            )
    return shape_score


def _checked_args(windows, sample_rate_hz, onset_index):
    """(windows (K, 4, M) float, fs [Hz], onsets (K,) int) of `common_mode_interference`,
    checked (ValueError)."""
    x = np.asarray(windows, dtype=float)
    if x.ndim != 3 or x.shape[1] != 4:
        raise ValueError(f"windows must be (K, 4, M), got shape {x.shape}")
    k = x.shape[0]
    fs = float(sample_rate_hz)
    if not (math.isfinite(fs) and fs > 0):
        raise ValueError(f"sample_rate_hz must be positive, got {sample_rate_hz!r}")
    on = np.asarray(onset_index, dtype=np.int64).reshape(-1)
    if on.size == 1 and k != 1:
        on = np.full(k, int(on[0]))
    if on.shape != (k,):
        raise ValueError(f"onset_index must have one entry per packet ({k}), got {on.shape}")
    return x, fs, on


def _model(acoustic, fs, front_end, low_max, high_max):
    """(the learnt model whose templates the shape test uses, or None for the nominal
    front end's; the spectrum tests' limits [1]): the device's own model once it is ready
    at this rate, its templates only where the nominal ones miss its touches."""
    if acoustic is None or not acoustic.ready(fs):
        return None, low_max, high_max
    low_max, high_max = acoustic.low_max(fs, low_max), acoustic.high_max(fs, high_max)
    if not acoustic.nominal_misfit(fs, front_end, _nominal_residual):
        return None, low_max, high_max  # the nominal front end describes the device
    return acoustic, low_max, high_max


def _nominal_residual(waves, sample_rate_hz, front_end) -> np.ndarray:
    """What the front end's templates (the shape test's, ``front_end`` a `PulseModel` or
    (high-pass Hz, order, low-pass Hz or None, order)) leave unexplained of each unit-norm
    waveform ``waves`` (J, L) [1]: 1 - the best squared correlation over offsets and lags."""
    tpls = _lag_templates(float(sample_rate_hz), waves.shape[1], SHAPE_LAGS, front_end)
    c = waves @ tpls.T
    return 1.0 - (c * c).max(axis=1)


def _echo_scores(score, s_full, on, cand, common, fs, geometry, echo_min) -> None:
    """Raise ``score[cand]`` (in place) for common-mode packets whose wall echo at 2R/c
    (regression coefficient beta of the common mode ``s_full`` at that lag on the direct
    packet) is weaker than ``|beta| >= echo_min``."""
    m = s_full.shape[1]
    lag = int(round(2.0 * geometry.radius_m / geometry.sound_speed_m_s * fs))
    wd = max(2, min(lag, int(round(5e-6 * fs))))
    if m >= lag + wd:
        a0 = np.clip(on[cand] - 1, 0, max(0, m - lag - wd))
        i0 = a0[:, None] + np.arange(wd)[None, :]
        direct, echo = s_full[cand[:, None], i0], s_full[cand[:, None], i0 + lag]
        ed = np.einsum("kw,kw->k", direct, direct)
        beta = np.einsum("kw,kw->k", direct, echo) / np.maximum(ed, 1e-30)
        score[cand] = np.maximum(
            score[cand], common[cand] * (1.0 - np.minimum(np.abs(beta) / echo_min, 1.0)) * 2.0
        )


def common_mode_interference(
    windows, sample_rate_hz: float, onset_index, *, geometry=None, noise_rms_v=None,
    lowpass_hz: float | str = "auto", window_s: float = 20e-6, echo_min: float | None = None,
    common_min: float = COMMON_MIN, highpass_hz: float = 100e3, highpass_order: int = 2,
    lowpass_order: int | str = "auto", shape_min: float | None = SHAPE_MIN,
    shape_z: float = 5.0, low_max: float = LOW_MAX, high_max: float = HIGH_MAX,
    acoustic=None, pulse=None,
):
    """(mask (K,) bool: interference, score (K,) float) for packets ``windows`` (K, 4, M)
    volts at ``sample_rate_hz`` with onsets ``onset_index`` (K,) (window-relative samples).

    ``noise_rms_v``: per-channel noise sigma (scalar or (K,)), removed from the energies
    (None: estimated per packet from the samples before the onset, when there are >= 8).
    ``lowpass_hz``, ``lowpass_order``: the front end's anti-alias low-pass ("auto": the
    default front end at this rate, `ae_tactile.geometry.front_end_lowpass`);
    ``window_s``: analysis length after the onset. ``echo_min`` (needs ``geometry``):
    on a device with wall echoes, a common-mode packet whose echo at 2R/c (regression
    coefficient beta of the common mode at that lag on the direct packet, -0.5 for the
    simulator's wall) is weaker than ``|beta| >= echo_min`` is interference too (catches
    interference shaped by the front end); None: no echo test (a device without echoes).
    ``shape_min``: the share of an acoustic packet's energy the acoustic templates
    explain at least (None: no shape test); ``shape_z``: how many standard deviations of
    the noise the unexplained energy must exceed before the shape test can reject (no shape
    test without a noise level: neither given nor >= 8 pretrigger samples).
    ``acoustic``: the device's own model of an acoustic packet
    (`ae_tactile.dsp.acoustic_model.AcousticLearner`); once it is ready at this rate its
    waveforms are the shape test's templates and its limits the spectrum tests' (at least
    ``low_max``, ``high_max``), instead of the nominal front end's.
    ``pulse``: the device's front end as a `PulseModel` (stated, `LocalizationConfig.
    front_end`, or calibrated on its touches), or a tuple of them (the stated one over the
    emission decays, `ae_tactile.localization.front_end.decay_family`): their pulses give
    the templates and the spectrum tests' limits, the first's low-pass the band, in place
    of ``highpass_*`` / ``lowpass_*``.
    Non-finite windows give mask False and score NaN (the localizer rejects them)."""
    x, fs, on = _checked_args(windows, sample_rate_hz, onset_index)
    k, _, m = x.shape
    if k == 0:
        return np.zeros(0, bool), np.zeros(0)
    if pulse is not None:
        lowpass_hz, front_end = _pulses(pulse)[0].lowpass_hz, pulse
    else:
        lowpass_hz, lowpass_order = _front_end_lowpass(fs, lowpass_hz, lowpass_order)
        front_end = (float(highpass_hz), int(highpass_order), lowpass_hz, int(lowpass_order))
    w = max(4, min(m, int(round(window_s * fs))))
    f_top = 0.5 * fs if lowpass_hz is None else min(lowpass_hz, 0.5 * fs)
    if pulse is not None:  # the spectrum a stated front end's packet has
        low_pulse, high_pulse = _pulse_limits(fs, w, front_end, f_top)
        low_max, high_max = max(low_max, low_pulse), max(high_max, high_pulse)
    learned, low_max, high_max = _model(acoustic, fs, front_end, low_max, high_max)
    start = np.clip(on - 1, 0, max(0, m - w))
    s_full = x.mean(axis=1)  # (K, M) common mode
    q_full = np.einsum("kcm,kcm->km", x, x) * 0.25  # (K, M) mean channel power
    rows = np.arange(k)[:, None]
    idx = start[:, None] + np.arange(w)[None, :]
    s = s_full[rows, idx]
    nv, nv_rel_var, noise_known = _noise_power(x, on, noise_rms_v)
    e_ch = q_full[rows, idx].sum(axis=1) - w * nv
    e_s = np.einsum("kw,kw->k", s, s) - w * nv * 0.25
    tiny = 1e-30
    common = np.clip(e_s / np.maximum(e_ch, tiny), 0.0, 1.0)
    mean = s.sum(axis=1) / w
    low = np.maximum((mean * mean * w - nv * 0.25) / np.maximum(e_s, tiny), 0.0)
    d = s[:, 1:] - s[:, :-1]
    band = 2.0 * (1.0 - math.cos(2.0 * math.pi * f_top / fs))
    e_d = np.einsum("kw,kw->k", d, d) - (w - 1) * nv * 0.5
    high = np.maximum(e_d / np.maximum(e_s * band, tiny), 0.0)
    score = common * np.maximum(low * (1.0 / low_max), high * (1.0 / high_max))
    # the shape and echo tests only for common-mode packets not yet flagged (most touches
    # are off the apex: common mode < common_min, nothing more to compute)
    cand = np.flatnonzero((common >= common_min) & ~(score >= 1.0))
    if shape_min is not None and cand.size and noise_known:
        shape_score = _shape_scores(x, on, cand, common, nv, nv_rel_var, w, fs, geometry,
                                    front_end, shape_min, shape_z, learned)
        score[cand] = np.maximum(score[cand], shape_score)
    if echo_min is not None and geometry is not None and cand.size:
        _echo_scores(score, s_full, on, cand, common, fs, geometry, echo_min)
    finite = np.isfinite(score) & np.isfinite(e_ch)
    score = np.where(finite, np.where(e_s > 0, score, 0.0), np.nan)
    mask = finite & (common >= common_min) & (score >= 1.0)
    return mask, score


#: The learned echo test (`EchoLearner`): it engages once ECHO_LEARN_N touches away from the
#: apex have been measured and the median of their echo ratios |beta| is at least
#: ECHO_LEARN_MIN (a device whose echoes are weaker has no usable echo: no test); its
#: threshold is ECHO_LEARN_MARGIN of that median (an apex touch's |beta| scatters round the
#: device's ratio by its noise: 0.05 at 20 dB in the window); the median of the last
#: ECHO_LEARN_KEEP measurements.
ECHO_LEARN_N = 3
ECHO_LEARN_MIN = 0.15
ECHO_LEARN_MARGIN = 0.5
ECHO_LEARN_KEEP = 64
#: a measurement needs the direct wave's energy in the window above this multiple of the
#: noise's (20 dB: the ratio's noise is then <= 0.1 / sqrt(channels))
ECHO_LEARN_SNR = 100.0


def echo_ratio(windows, sample_rate_hz: float, onset_index, points_m, geometry,
               noise_rms_v=None) -> np.ndarray:
    """The first wall echo's amplitude over the direct wave's, beta (K,), of packets
    ``windows`` (K, 4, M) volts whose emissions were localized at ``points_m`` (K, 3).

    The echo reaches element k over 2R + |s + e_k| against |s - e_k| for the direct wave
    (`ae_tactile.sim.propagation`); per channel the window of w = min(2R/c, 5 us) samples
    from its direct arrival (onset - 1 + the localized delay) is regressed on the same
    window at its echo's lag: beta = sum_k <d_k, e_k> / sum_k <d_k, d_k> (the concave wall
    refocuses the echo: its amplitude over the direct wave's is the wall's reflection
    coefficient, about the same for every contact point). NaN where the window does not
    hold the echo, or the direct wave's energy is below ECHO_LEARN_SNR times the noise's
    (``noise_rms_v``, else estimated from >= 8 samples before the onset, else no test)."""
    x = np.asarray(windows, dtype=float)
    pts = np.asarray(points_m, dtype=float).reshape(-1, 3)
    if x.ndim != 3 or x.shape[1] != 4 or pts.shape[0] != x.shape[0]:
        raise ValueError(f"windows must be (K, 4, M) with K points, got {x.shape}, {pts.shape}")
    k, _, m = x.shape
    fs = float(sample_rate_hz)
    on = np.broadcast_to(np.asarray(onset_index, dtype=np.int64).reshape(-1), (k,))
    out = np.full(k, np.nan)
    if k == 0:
        return out
    c = geometry.sound_speed_m_s
    e = geometry.element_positions_m  # (4, 3)
    direct = np.linalg.norm(pts[:, None, :] - e[None], axis=2)  # (K, 4)
    echo = 2.0 * geometry.radius_m + np.linalg.norm(pts[:, None, :] + e[None], axis=2)
    first = direct.min(axis=1, keepdims=True)
    lag = int(round(2.0 * geometry.radius_m / c * fs))
    wd = max(2, min(lag, int(round(5e-6 * fs))))
    with np.errstate(invalid="ignore"):
        i_d = on[:, None] - 1 + np.rint((direct - first) / c * fs)
        i_e = on[:, None] - 1 + np.rint((echo - first) / c * fs)
    ok = np.isfinite(i_d).all(axis=1) & np.isfinite(i_e).all(axis=1)
    ok &= (np.where(np.isfinite(i_d), i_d, -1).min(axis=1) >= 0)
    ok &= (np.where(np.isfinite(i_e), i_e, m).max(axis=1) + wd <= m)
    rows = np.flatnonzero(ok)
    if rows.size == 0:
        return out
    ar = np.arange(wd)
    ch = np.arange(4)[None, :, None]
    d = x[rows[:, None, None], ch, i_d[rows].astype(np.int64)[:, :, None] + ar]  # (R, 4, wd)
    ec = x[rows[:, None, None], ch, i_e[rows].astype(np.int64)[:, :, None] + ar]
    ed = np.einsum("rcw,rcw->r", d, d)
    beta = np.einsum("rcw,rcw->r", d, ec) / np.maximum(ed, 1e-30)
    if noise_rms_v is not None:
        nv = np.broadcast_to(np.asarray(noise_rms_v, float).reshape(-1) ** 2, (k,))[rows]
    elif int(on.min()) - 2 >= 8:
        pre = x[rows, :, : int(on.min()) - 2]
        nv = pre.var(axis=2).mean(axis=1)
    else:
        nv = np.zeros(rows.size)
    good = np.isfinite(beta) & (ed > ECHO_LEARN_SNR * 4 * wd * nv) & (ed > 0)
    out[rows[good]] = beta[good]
    return out


class EchoLearner:
    """The echo test's threshold learnt from the device's own touches: on a fingertip with
    wall echoes every acoustic packet carries its echo at 2R/c, interference shaped by the
    front end none. `add` the `echo_ratio` of touches away from the apex (never
    interference); `echo_min` is ECHO_LEARN_MARGIN x median |beta| of the last
    ECHO_LEARN_KEEP once ECHO_LEARN_N were seen and that median is >= ECHO_LEARN_MIN, else
    None (no echo test: a device without echoes, or not yet learnt)."""

    def __init__(self):
        self._betas: list[float] = []
        #: echo ratios measured so far (all, not only the kept ones)
        self.n_measured = 0

    def add(self, betas) -> None:
        b = np.asarray(betas, dtype=float).reshape(-1)
        b = b[np.isfinite(b)]
        if b.size:
            self._betas.extend(b.tolist())
            del self._betas[:-ECHO_LEARN_KEEP]
            self.n_measured += int(b.size)

    def reset(self) -> None:
        self._betas.clear()
        self.n_measured = 0

    @property
    def ratio(self) -> float | None:
        """The device's echo ratio |median beta| (None before ECHO_LEARN_N touches)."""
        if len(self._betas) < ECHO_LEARN_N:
            return None
        return abs(float(np.median(self._betas)))

    @property
    def echo_min(self) -> float | None:
        r = self.ratio
        return None if r is None or r < ECHO_LEARN_MIN else ECHO_LEARN_MARGIN * r

    def calibration_state(self) -> dict | None:
        """The echo ratios measured (`ae_tactile.calibration.CalibrationStore`'s section;
        None: none yet)."""
        if not self._betas:
            return None
        return {"format": 1, "betas": [float(b) for b in self._betas],
                "n_measured": int(self.n_measured)}

    def load_calibration(self, state: dict) -> None:
        """Start from a saved `calibration_state` (ValueError: unusable, nothing changed)."""
        if not isinstance(state, dict) or state.get("format") != 1:
            raise ValueError("echo: unknown format")
        b = np.asarray(state.get("betas", ()), dtype=float).reshape(-1)
        if not (np.isfinite(b).all() and (np.abs(b) <= 1.0).all()):
            raise ValueError("echo: ratios out of range")
        self._betas = b[-ECHO_LEARN_KEEP:].tolist()
        self.n_measured = max(int(state.get("n_measured", b.size)), len(self._betas))
