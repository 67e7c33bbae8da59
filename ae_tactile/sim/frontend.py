# SPDX-License-Identifier: Apache-2.0
"""Front end: PVDF + amplifier gain, high-pass, anti-alias low-pass, noise, ADC.

The analog chain is the rational transfer function (volts per pascal)

    F(s) = G * HP(s) * LP_m(s) [* AMP(s)]

with G = ``sensitivity_v_per_pa``, HP an n-th order Butterworth high-pass at
``highpass_hz`` (paper: 100 kHz, n = 2) or a cascade of first-order RC stages
(``highpass_rc_hz``), LP_m an m-th order low-pass at ``lowpass_hz`` (Butterworth by
default, 1 MHz: the PVDF/amplifier band and the ADC's anti-alias filter; Bessel or
Chebyshev-I by ``lowpass_family``) and AMP an optional amplifier pole. All stages are
given as analog zpk (`analog_stages`); the poles must be simple.
It is applied causally, as the analog front end would be. Because the emission (Eq. 9)
is rational too, the filtered response to each arrival is a finite sum of complex
exponentials, evaluated *exactly* at the sample instants (see `response.py`); sampling
then aliases whatever the low-pass lets through above fs/2, as a real ADC does.

Noise: Gaussian, variance sigma^2 per channel, added at the ADC input: white (ADC
noise) and, for a share ``amplifier_noise_share`` of the variance, amplifier noise, white
at the amplifier input and coloured by the whole analog chain (`AmplifierNoise`).
SNR (docs/conventions.md): SNR_dB = 10 log10(P_signal / sigma^2), P_signal the
mean power of the noise-free signal over the 4 channels and the 30 us window that
starts at the earliest direct arrival. `noise_rms_for_snr` is the one conversion.

ADC: codes = clip(round(v / LSB), -2^(b-1), 2^(b-1) - 1), LSB = 2 FS / 2^b; the
output in volts is codes * LSB.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import signal

from ae_tactile.geometry import front_end_stages
from ae_tactile.sim.propagation import path_lengths
from ae_tactile.sim.response import att_support_samples, fast_support_samples

#: Length of the SNR window after the earliest direct arrival (docs/conventions.md).
SNR_WINDOW_S = 30e-6


def analog_stages(config) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The analog chain as a list of stages (zeros, poles [rad/s], gain), without the
    sensitivity: the high-pass (Butterworth, or one first-order RC stage per corner of
    ``highpass_rc_hz``), the anti-alias low-pass of ``lowpass_family``, and the optional
    amplifier pole. F(s) = sensitivity * product of the stages.

    Parameters
    ----------
    config : SimConfig

    Returns
    -------
    list of (ndarray, ndarray, float)
    """
    return front_end_stages(
        config.highpass_hz, config.highpass_order, config.highpass_rc_hz, config.lowpass_hz,
        config.lowpass_order, config.lowpass_family, config.lowpass_ripple_db,
        config.amplifier_pole_hz)


class FrontEnd:
    """Poles, residues and exponential tables of F(s) for one `SimConfig` (built lazily
    via ``config.frontend``)."""

    def __init__(self, config):
        self.config = config
        stages = analog_stages(config)
        zs = [z for z, _, _ in stages]
        ps = [p for _, p, _ in stages]
        ks = [k for _, _, k in stages]
        self.zeros = np.concatenate(zs).astype(complex)
        self.poles = np.concatenate(ps).astype(complex)
        self.gain = float(np.prod(ks)) * config.sensitivity_v_per_pa
        # F(s) -> gain * s^(nz - np): direct term only when as many zeros as poles.
        self.direct = self.gain if len(self.zeros) == len(self.poles) else 0.0
        # Keep one pole of each conjugate pair (Im > 0) plus the real poles; a pair
        # contributes 2 Re(c e^{q t}), a real pole c e^{q t}.
        p = self.poles
        keep = p.imag > 1e-9 * np.abs(p)
        real = np.abs(p.imag) <= 1e-9 * np.abs(p)
        self.fast_poles = np.concatenate([p[keep], p[real].real.astype(complex)])
        self.fast_weights = np.concatenate([np.full(keep.sum(), 2.0), np.ones(real.sum())])
        self.fast_residues = np.array([self._residue(q) for q in self.fast_poles])
        # Slowest filter pole sets how long the fast part lasts.
        self.fast_decay_rate = float(np.min(-self.fast_poles.real))
        #: config-constant truncation lengths (samples) of the fast / attenuation parts
        self.support_fast = fast_support_samples(config, self)
        r = config.geometry.radius_m
        far = np.array([[r, 0.0, 0.0]])
        self.max_path_m = float(path_lengths(far, config).max()) + config.geometry.element_offset_m
        self.support_att = att_support_samples(config, self.max_path_m)

    def _residue(self, q):
        others = [pp for pp in self.poles if abs(pp - q) > 1e-9 * abs(q)]
        if len(others) != len(self.poles) - 1:
            raise ValueError("the front end's poles must be simple (two stages share a pole"
                             f" at {q / (2 * math.pi):.6g} rad/s / 2 pi)")
        return self.gain * np.prod(q - self.zeros) / np.prod(q - np.array(others))

    @property
    def amplifier_noise(self) -> AmplifierNoise:
        """Cached `AmplifierNoise` of this chain."""
        a = getattr(self, "_amp_noise", None)
        if a is None:
            a = self._amp_noise = AmplifierNoise(self)
        return a

    def transfer(self, s):
        """F(s) (V/Pa) at complex or real s (any shape)."""
        s = np.asarray(s, dtype=complex)
        num = np.ones_like(s)
        for z in self.zeros:
            num = num * (s - z)
        den = np.ones_like(s)
        for p in self.poles:
            den = den * (s - p)
        return self.gain * num / den

    def frequency_response(self, f_hz):
        """F(j 2 pi f) (V/Pa)."""
        return self.transfer(2j * math.pi * np.asarray(f_hz, dtype=float))

    def exp_table(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(Re, Im) of e^{q_j dt k}, shape (n_fast, n) each, for k = 0..n-1 (cached)."""
        cached = getattr(self, "_table", None)
        if cached is None or cached[0].shape[1] < n:
            k = np.arange(max(n, self.config.max_support_samples), dtype=float)
            e = np.exp(self.fast_poles[:, None] * (self.config.dt_s * k)[None, :])
            self._table = (np.ascontiguousarray(e.real), np.ascontiguousarray(e.imag))
        re, im = self._table
        return re[:, :n], im[:, :n]

    @property
    def fast_basis(self) -> np.ndarray:
        """[Re E; Im E] stacked, (2 n_fast, max_support_samples), C-contiguous (cached)."""
        b = getattr(self, "_basis", None)
        if b is None:
            re, im = self.exp_table(self.config.max_support_samples)
            b = self._basis = np.ascontiguousarray(np.vstack([re, im]))
        return b


# ------------------------------------------------------------------------ amplifier noise
#: Oversampling of the amplifier-noise filter: the analog chain is discretized by the
#: bilinear transform at NOISE_OVERSAMPLING fs and the output decimated (a sample of every
#: NOISE_OVERSAMPLING). At 8 fs the bilinear frequency warping is below 0.2 % at fs / 2
#: and the spectrum folded from above 4 fs is below 1e-3 of the variance for any low-pass
#: of order >= 2 at or below fs / 2; the sampled noise aliases what the chain passes
#: above fs / 2, as a real ADC does. (An exact discretization of the state space is
#: ill-conditioned at order 10 and poles three decades apart.)
NOISE_OVERSAMPLING = 8


class AmplifierNoise:
    """Unit-variance amplifier noise at the ADC: white at the amplifier input, filtered by
    the analog chain F(s) / G (see `NOISE_OVERSAMPLING` for the discretization).

    Parameters
    ----------
    frontend : FrontEnd
        The chain's zeros, poles and gain.
    """

    def __init__(self, frontend):
        cfg = frontend.config
        self.factor = NOISE_OVERSAMPLING
        fs_up = self.factor * float(cfg.sample_rate_hz)
        z, p, k = signal.bilinear_zpk(frontend.zeros, frontend.poles,
                                      frontend.gain / cfg.sensitivity_v_per_pa, fs_up)
        self.sos = signal.zpk2sos(z, p, k)
        slowest = float(np.min(np.abs(frontend.poles.real)))       # [rad/s]
        #: up-rate samples of filter start-up discarded: e^-14 of the slowest pole
        self.burn = int(math.ceil(14.0 / slowest * fs_up))
        imp = np.zeros(2 * self.burn)
        imp[0] = 1.0
        self.impulse = signal.sosfilt(self.sos, imp)
        #: variance of the filtered unit white noise (sum of h^2)
        self.variance = float(np.sum(self.impulse ** 2))

    def autocorrelation(self, n_lags: int) -> np.ndarray:
        """Normalised autocovariance r[m], m = 0..n_lags-1, of the noise at the ADC
        (r[0] = 1), exact for the discretized chain.

        Parameters
        ----------
        n_lags : int

        Returns
        -------
        ndarray
        """
        h = self.impulse
        k = self.factor
        r = [np.dot(h[:h.size - k * m], h[k * m:]) if k * m < h.size else 0.0
             for m in range(int(n_lags))]
        return np.asarray(r) / self.variance

    def draw(self, shape, gen, rows_per_batch: int = 256) -> np.ndarray:
        """Unit-variance noise of ``shape`` (..., M) at the ADC rate.

        Parameters
        ----------
        shape : tuple of int
        gen : numpy.random.Generator

        Returns
        -------
        ndarray
        """
        shape = tuple(shape)
        m_len = shape[-1]
        rows = int(np.prod(shape[:-1]))
        out = np.empty((rows, m_len))
        n_up = self.burn + self.factor * m_len
        scale = 1.0 / math.sqrt(self.variance)
        for r0 in range(0, rows, rows_per_batch):
            r1 = min(rows, r0 + rows_per_batch)
            y = signal.sosfilt(self.sos, gen.standard_normal((r1 - r0, n_up)), axis=-1)
            out[r0:r1] = y[:, self.burn::self.factor][:, :m_len] * scale
        return out.reshape(shape)


# ------------------------------------------------------------------------ SNR / noise
def signal_power_v2(clean_v, onset_index, sample_rate_hz, window_s=SNR_WINDOW_S):
    """Mean power (V^2) of noise-free packets over the 4 channels and the SNR window.

    ``clean_v`` (N, 4, M); ``onset_index`` (N,) the first sample at or after the earliest
    direct arrival. The window holds round(window_s * fs) samples from the onset; it must
    fit inside the packet (ValueError otherwise).
    """
    x = np.asarray(clean_v, dtype=float)
    if x.ndim != 3 or x.shape[1] != 4:
        raise ValueError(f"clean_v must have shape (N, 4, M), got {x.shape}")
    on = np.asarray(onset_index, dtype=np.int64).reshape(-1)
    if on.shape[0] != x.shape[0]:
        raise ValueError("onset_index must have one entry per packet")
    w = int(round(window_s * float(sample_rate_hz)))
    if w < 1:
        raise ValueError("SNR window shorter than one sample")
    if np.any(on < 0) or np.any(on + w > x.shape[2]):
        raise ValueError(f"the {window_s * 1e6:g} us SNR window after the onset does not fit in"
                         f" packets of {x.shape[2]} samples")
    e = np.concatenate([np.zeros((x.shape[0], 1)), np.cumsum(np.sum(x * x, axis=1), axis=1)],
                       axis=1)
    rows = np.arange(x.shape[0])
    return (e[rows, on + w] - e[rows, on]) / (4.0 * w)


def noise_rms_for_snr(signal_power_v2_, snr_db):
    """sigma_n (V) such that 10 log10(P_signal / sigma_n^2) = snr_db (conventions.md)."""
    p = np.asarray(signal_power_v2_, dtype=float)
    snr = np.asarray(snr_db, dtype=float)
    if np.any(~np.isfinite(snr)):
        raise ValueError(f"snr_db must be finite, got {snr_db!r}")
    return np.sqrt(p / 10.0 ** (snr / 10.0))


def snr_db_from_noise(signal_power_v2_, noise_rms_v):
    """Inverse of `noise_rms_for_snr`: 10 log10(P_signal / sigma_n^2)."""
    p = np.asarray(signal_power_v2_, float)
    return 10.0 * np.log10(p / np.asarray(noise_rms_v, float) ** 2)


def noise_rms_from_density(density_v_per_rthz, sample_rate_hz):
    """sigma_n = density * sqrt(fs / 2): white noise over 0..fs/2."""
    return float(density_v_per_rthz) * math.sqrt(float(sample_rate_hz) / 2.0)


# ------------------------------------------------------------------------ ADC
def quantize(v, config, out=None):
    """ADC: volts -> codes * LSB with clipping at full scale. Returns (volts, clipped_mask)."""
    lsb = config.lsb_v
    half = 1 << (config.adc_bits - 1)
    codes = np.rint(np.multiply(v, 1.0 / lsb, out=out))
    clipped = (codes < -half) | (codes > half - 1)
    np.clip(codes, -half, half - 1, out=codes)
    codes *= lsb
    return codes, clipped


def to_codes(v, config):
    """ADC codes (int16 for <= 16 bits, else int32) of already-quantized volts."""
    dtype = np.int16 if config.adc_bits <= 16 else np.int32
    return np.rint(np.asarray(v) / config.lsb_v).astype(dtype)
