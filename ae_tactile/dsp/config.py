# SPDX-License-Identifier: Apache-2.0
"""Parameters of the packet detector, in SI units, validated; converted to samples once.

See docs/detection.md for the meaning of every parameter and why the defaults are what
they are. All times are seconds; ``DetectorConfig.samples()`` converts them to integer
sample counts for the configured sample rate (rounded, with small minimums so that the
detector still works at 1 MS/s).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

from .filters import LOWPASS_MAX_FRACTION


def _num(name, value, *, lo=None, hi=None, lo_open=False, allow_none=False):
    if value is None and allow_none:
        return None
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ValueError(f"{name} must be {'>' if lo_open else '>='} {lo:g}, got {value!r}")
    if hi is not None and v > hi:
        raise ValueError(f"{name} must be <= {hi:g}, got {value!r}")
    return v


def _int(name, value, lo, hi):
    if isinstance(value, bool) or not isinstance(value, int) and not hasattr(value, "__index__"):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    v = int(value.__index__()) if not isinstance(value, int) else value
    if not lo <= v <= hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return v


@dataclass(frozen=True)
class SampleParams:
    """DetectorConfig times in samples (see DetectorConfig.samples).

    The trigger path runs at trigger_rate_hz = fs / decim: hold, onset_window,
    onset_decay (per trigger sample, energy), channel_refractory, min_separation, hdt,
    hlt, echo_*, block and settle count *trigger* samples; everything
    else (windows, AIC, features, block_full) counts input samples.
    """

    decim: int
    trigger_rate_hz: float
    pretrigger: int
    posttrigger: int
    window: int
    hold: int
    onset_window: int
    onset_decay: float
    channel_refractory: int
    channel_spread: int
    min_separation: int
    hdt: int
    hlt: int
    echo_delay: int
    echo_tolerance: int
    aic_pre: int
    reonset_aic_pre: int
    aic_post: int
    block: int
    block_full: int
    settle: int
    noise_guard: int
    peak_window: int
    polarity_window: int
    snr_window: int
    release_lag: int
    min_batch: int
    history: int


@dataclass(frozen=True)
class DetectorConfig:
    """Packet-detector parameters (SI units). Defaults suit the paper's sensor at 10 MS/s.

    Filter (trigger path only; windows carry the original samples)
      sample_rate_hz      ADC rate (Hz), 0.25 .. 1000 MS/s (tested 1 - 20 MS/s).
      trigger_min_rate_hz the trigger path runs on sums of D consecutive samples,
                          D = max(1, floor(fs / trigger_min_rate_hz)) (3 MS/s: D = 3 at
                          10 MS/s, 6 at 20 MS/s, 1 below 6 MS/s). Cuts the cost of the
                          trigger; onsets and windows use the full rate.
      highpass_hz         Butterworth high-pass corner (100 kHz, the paper's band edge).
      lowpass_hz          Butterworth low-pass corner (1.5 MHz; clipped to 0.36 of the
                          trigger rate, dropped below 4 highpass_hz); None: none.
      filter_order        order of each of the two (2).
    Trigger (on the channel-RMS envelope e = sqrt(mean_k y_k^2 / sigma_k^2), in noise sigmas)
      threshold_sigma     a hit starts when e reaches this (5).
      rearm_sigma         hysteresis: the trigger re-arms only after e stayed below this
                          for envelope_hold_s (3).
      envelope_hold_s     peak-hold of the envelope for the hysteresis, longer than the
                          gaps at the waveform's zero crossings (2 us).
    Re-trigger inside a running packet (per-channel onsets, docs/detection.md)
      channel_onset_sigma a channel onset needs the channel's first difference of the
                          band-passed signal to reach this many of its noise sigmas (6) ...
      jump_ratio          ... and this times its exponentially decayed maximum over the
                          preceding onset_window_s (3, amplitude ratio) ...
      onset_window_s      (4 us)
      onset_decay_s       amplitude decay time of that maximum (3 us).
      channel_refractory_s  a channel's second onset within one hit, at least this long
                          after its first, starts a new emission (2 us) ...
      channel_spread_s    ... unless an emission was accepted less than this before it
                          (it is then that emission's late channel): the largest arrival
                          spread over the 4 elements, 2 sqrt(2) a / c (2.9 us for the
                          paper's water tip; set 4.3 us for silicone) (3 us).
      min_separation_s    onsets closer than this are one emission (2 us).
    Acoustic-emission timing rules
      hit_definition_time_s   HDT: a hit ends when e stayed below rearm_sigma this long (10 us).
      hit_lockout_time_s      HLT: no new hit starts within HLT after a hit ended (0: off,
                              so that every emission gets a window).
    Wall echoes (off by default)
      echo_delay_s        delay of the first wall echo after the direct wave (2 R / c:
                          13.5 us for the paper's water tip). When set, a re-trigger whose
                          crossing lies within echo_tolerance_s of k * echo_delay_s
                          (k = 1 .. echo_orders) after an accepted emission's crossing is
                          taken for its echo: counted, no window. None: every re-trigger
                          gets a window (echoes then appear as in-hit emissions).
    Windows
      pretrigger_s, posttrigger_s   window = [onset - pre, onset + post) (10 us, 30 us).
      aic_pre_s, aic_post_s         AIC search segment [crossing - pre, crossing + post)
                                    (4 us, 1 us).
      reonset_aic_pre_s   for an emission found by a channel re-onset (inside a running
                          packet) the AIC may not pick earlier than this before it (3 us),
                          nor before the previous emission's crossing + channel_spread_s.
    Noise floor (see ae_tactile/dsp/noise.py)
      noise_block_s (100 us), noise_history_blocks (16), noise_min_blocks (2),
      noise_epoch_blocks (16), burst_ratio (6), settle_s (20 us).
    ADC (saturation and sanity)
      full_scale_v        the ADC's full scale at the input of the detector (V): codes
                          span [-FS, FS (1 - 2^(1-bits))]. The driver sets it to
                          volts_per_count * 2^(bits - 1).
      adc_bits            (12). A sample within half an LSB of either rail is saturated.
      max_abs_v           samples beyond this are invalid, like NaN (None: 1000 FS).
    Per-packet features
      noise_guard_s       pre-onset samples this close to the onset are left out of the
                          noise estimate (0.3 us).
      peak_window_s, polarity_window_s, snr_window_s   after the onset (5 us, 1 us, 30 us).
    Throughput
      min_batch_s         chunks shorter than this are gathered before processing (1 ms):
                          per-call overhead vs latency; the output does not depend on it.
    """

    sample_rate_hz: float = 10e6
    trigger_min_rate_hz: float = 3e6
    highpass_hz: float = 100e3
    lowpass_hz: float | None = 1.5e6
    filter_order: int = 2
    threshold_sigma: float = 5.0
    rearm_sigma: float = 3.0
    envelope_hold_s: float = 2e-6
    channel_onset_sigma: float = 6.0
    jump_ratio: float = 3.0
    onset_window_s: float = 4e-6
    onset_decay_s: float = 3e-6
    channel_refractory_s: float = 2e-6
    channel_spread_s: float = 3e-6
    min_separation_s: float = 2e-6
    hit_definition_time_s: float = 10e-6
    hit_lockout_time_s: float = 0.0
    echo_delay_s: float | None = None
    echo_orders: int = 2
    echo_tolerance_s: float = 1.5e-6
    pretrigger_s: float = 10e-6
    posttrigger_s: float = 30e-6
    aic_pre_s: float = 4e-6
    aic_post_s: float = 1e-6
    reonset_aic_pre_s: float = 3e-6
    noise_block_s: float = 100e-6
    noise_history_blocks: int = 16
    noise_min_blocks: int = 2
    noise_epoch_blocks: int = 16
    burst_ratio: float = 6.0
    settle_s: float = 20e-6
    full_scale_v: float = 1.0
    adc_bits: int = 12
    max_abs_v: float | None = None
    noise_guard_s: float = 0.3e-6
    min_batch_s: float = 1e-3
    peak_window_s: float = 5e-6
    polarity_window_s: float = 1e-6
    snr_window_s: float = 30e-6

    def __post_init__(self) -> None:
        fs = _num("sample_rate_hz", self.sample_rate_hz, lo=250e3, hi=1e9)
        _num("trigger_min_rate_hz", self.trigger_min_rate_hz, lo=250e3)
        ft = fs / self.decimation
        hp = _num("highpass_hz", self.highpass_hz, lo=0.0, lo_open=True)
        if hp >= LOWPASS_MAX_FRACTION * ft:
            raise ValueError(
                f"highpass_hz={self.highpass_hz!r} must be below "
                f"{LOWPASS_MAX_FRACTION} * trigger rate = {LOWPASS_MAX_FRACTION * ft:g} Hz"
                f" (sample_rate_hz={fs:g}, trigger_min_rate_hz={self.trigger_min_rate_hz:g})"
            )
        lp = _num("lowpass_hz", self.lowpass_hz, lo=0.0, lo_open=True, allow_none=True)
        if lp is not None and lp <= hp:
            raise ValueError(
                f"lowpass_hz={self.lowpass_hz!r} must be above highpass_hz={self.highpass_hz!r}"
            )
        _int("filter_order", self.filter_order, 1, 8)
        on = _num("threshold_sigma", self.threshold_sigma, lo=0.0, lo_open=True, hi=1e6)
        off = _num("rearm_sigma", self.rearm_sigma, lo=0.0, lo_open=True)
        if off >= on:
            raise ValueError(
                f"rearm_sigma={self.rearm_sigma!r} must be below threshold_sigma="
                f"{self.threshold_sigma!r} (hysteresis)"
            )
        _num("jump_ratio", self.jump_ratio, lo=1.0, lo_open=True)
        _num("channel_onset_sigma", self.channel_onset_sigma, lo=0.0, lo_open=True)
        for name in (
            "envelope_hold_s",
            "onset_window_s",
            "onset_decay_s",
            "channel_refractory_s",
            "channel_spread_s",
            "min_separation_s",
            "reonset_aic_pre_s",
            "hit_definition_time_s",
            "posttrigger_s",
            "aic_pre_s",
            "aic_post_s",
            "noise_block_s",
            "peak_window_s",
            "polarity_window_s",
            "snr_window_s",
        ):
            _num(name, getattr(self, name), lo=0.0, lo_open=True, hi=1.0)
        _num("echo_delay_s", self.echo_delay_s, lo=0.0, lo_open=True, hi=1.0, allow_none=True)
        _int("echo_orders", self.echo_orders, 1, 16)
        for name in (
            "hit_lockout_time_s",
            "pretrigger_s",
            "settle_s",
            "noise_guard_s",
            "min_batch_s",
            "echo_tolerance_s",
        ):
            _num(name, getattr(self, name), lo=0.0, hi=1.0)
        m = _int("noise_history_blocks", self.noise_history_blocks, 1, 4096)
        _int("noise_min_blocks", self.noise_min_blocks, 1, m)
        _int("noise_epoch_blocks", self.noise_epoch_blocks, 1, 1 << 20)
        _num("burst_ratio", self.burst_ratio, lo=1.0, lo_open=True)
        _num("full_scale_v", self.full_scale_v, lo=0.0, lo_open=True)
        _int("adc_bits", self.adc_bits, 2, 32)
        mx = _num("max_abs_v", self.max_abs_v, lo=0.0, lo_open=True, allow_none=True)
        if mx is not None and mx < self.full_scale_v:
            raise ValueError(
                f"max_abs_v={self.max_abs_v!r} must be >= full_scale_v={self.full_scale_v!r}"
            )
        sp = self.samples()
        if sp.window > 1 << 20:
            raise ValueError(
                f"window of {sp.window} samples is too long (pretrigger_s + posttrigger_s)"
            )

    # ---------------------------------------------------------------- derived
    @property
    def decimation(self) -> int:
        """D: input samples summed per trigger-path sample."""
        return max(1, int(float(self.sample_rate_hz) // float(self.trigger_min_rate_hz)))

    @property
    def trigger_rate_hz(self) -> float:
        return float(self.sample_rate_hz) / self.decimation

    def samples(self) -> SampleParams:
        fs = float(self.sample_rate_hz)
        d = self.decimation
        ft = fs / d

        def n(t, lo):
            return max(int(lo), int(round(float(t) * fs)))

        def nt(t, lo):
            return max(int(lo), int(round(float(t) * ft)))

        pre = n(self.pretrigger_s, 0)
        post = n(self.posttrigger_s, 2)
        aic_post = n(self.aic_post_s, 3)
        # the crossing is known to a group of d samples: widen the AIC segment by d
        aic_pre = n(self.aic_pre_s, 4) + d - 1
        hold = nt(self.envelope_hold_s, 1)
        block = nt(self.noise_block_s, 32)
        release_lag = pre + aic_pre + aic_post
        return SampleParams(
            decim=d,
            trigger_rate_hz=ft,
            pretrigger=pre,
            posttrigger=post,
            window=pre + post,
            hold=hold,
            onset_window=nt(self.onset_window_s, 1),
            onset_decay=math.exp(-2.0 / (float(self.onset_decay_s) * ft)),
            channel_refractory=nt(self.channel_refractory_s, 1),
            channel_spread=nt(self.channel_spread_s, 1),
            min_separation=nt(self.min_separation_s, 1),
            hdt=nt(self.hit_definition_time_s, 1),
            hlt=nt(self.hit_lockout_time_s, 0),
            echo_delay=0 if self.echo_delay_s is None else nt(self.echo_delay_s, 1),
            echo_tolerance=nt(self.echo_tolerance_s, 0),
            aic_pre=aic_pre,
            aic_post=aic_post,
            reonset_aic_pre=n(self.reonset_aic_pre_s, 2) + d,
            block=block,
            block_full=block * d,
            settle=nt(self.settle_s, 0),
            noise_guard=n(self.noise_guard_s, 0),
            peak_window=n(self.peak_window_s, 1),
            polarity_window=n(self.polarity_window_s, 1),
            snr_window=n(self.snr_window_s, 1),
            release_lag=release_lag,
            min_batch=n(self.min_batch_s, 0),
            history=2 * pre + post + 2 * (aic_pre + aic_post) + 8 * d + 8,
        )

    @property
    def lsb_v(self) -> float:
        """ADC step 2 FS / 2^bits (V)."""
        return 2.0 * float(self.full_scale_v) / float(1 << int(self.adc_bits))

    @property
    def saturation_levels_v(self) -> tuple[float, float]:
        """(low, high): a sample <= low or >= high is at an ADC rail (half an LSB inside)."""
        lsb = self.lsb_v
        fs = float(self.full_scale_v)
        return -fs + 0.5 * lsb, fs - 1.5 * lsb

    @property
    def invalid_level_v(self) -> float:
        return (
            float(self.max_abs_v)
            if self.max_abs_v is not None
            else 1000.0 * float(self.full_scale_v)
        )

    def replace(self, **changes) -> "DetectorConfig":
        return replace(self, **changes)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "DetectorConfig":
        """From a mapping (e.g. ROS parameters); unknown keys raise ValueError."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown detector parameter(s): {unknown}")
        return cls(**d)
