# SPDX-License-Identifier: Apache-2.0
"""Hits in AE terms: threshold in dB_AE, duration discrimination (DDT/HDT), rearm (HLT).

A hit on one channel starts at the first sample whose magnitude reaches the threshold
and ends at the last crossing that follows the previous one by less than the duration
discrimination time (DDT, Mistras' HDT): the hit is over once DDT has passed without a
crossing. After that the channel stays deaf for the rearm time (Mistras' HLT) before a
crossing can start a new hit. 0 dB_AE is 1 uV at the sensor (40 dB_AE = 100 uV); the
preamplifier gain (dB) between the sensor and the recorded volts is taken off every
amplitude and energy, as the acquisition systems do.

Features per hit, as Vallen and Mistras define them: amplitude (largest magnitude; with a
peak definition time PDT, the first peak not exceeded within PDT), rise time (first
crossing to that peak), duration (first to last crossing), counts (rising crossings of
the positive threshold), energy (integral of the squared sensor voltage over the
duration, [V^2 s] and Vallen's [eu] = 1e-14 V^2 s). The onset is refined on the samples
with the AIC picker (`ae_tactile.dsp.onset.aic_pick`) over a window before and after the
first crossing, never earlier than the previous hit of the channel.

No blind start: the noise floor comes from the pre-trigger samples of a transient record,
or from the quietest stretches of a continuous one (`noise_floor_v`), so the first hit of
a file is found like any other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ae_tactile.dsp.onset import aic_pick

from .readers import Recording

#: 0 dB_AE at the sensor [V]
DB_AE_REF_V = 1e-6
#: Vallen's energy unit [V^2 s]
EU_V2S = 1e-14
#: pre-trigger samples next to the trigger left out of the noise floor (a slow rise)
NOISE_GUARD_SAMPLES = 8
#: block length of the continuous noise floor [s], and the share of blocks it keeps
NOISE_BLOCK_S = 50e-6
NOISE_QUIET_SHARE = 0.2
#: a threshold below this many noise rms fires on noise (warned)
MIN_THRESHOLD_NOISE_RATIO = 4.0
#: most hits kept per channel of one record (a threshold in the noise would make one per
#: few samples); `detect` warns when a channel reaches it
MAX_HITS_PER_CHANNEL = 100_000
#: longest AIC window side [samples] (bounds the work per hit at any sample rate), and
#: the most window samples per AIC call (bounds the memory: 8 MiB per float64 copy)
MAX_ONSET_SIDE_SAMPLES = 8192
AIC_CHUNK_SAMPLES = 1 << 20


def db_ae_to_v(db_ae) -> float:
    """Volts of a level in dB_AE (0 dB_AE = 1 uV)."""
    return DB_AE_REF_V * 10.0 ** (float(db_ae) / 20.0)


def v_to_db_ae(volts) -> float:
    """dB_AE of a level in volts (-inf for 0)."""
    v = float(volts)
    return 20.0 * math.log10(v / DB_AE_REF_V) if v > 0 else -math.inf


def _check(name: str, value, lo: float, optional: bool = False):
    if value is None and optional:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v >= lo):
        raise ValueError(f"{name} must be finite and >= {lo:g}, got {value!r}")
    return v


@dataclass(frozen=True)
class HitDefinition:
    """When a hit starts and ends, in the terms of AE acquisition systems.

    Parameters
    ----------
    threshold_db_ae : float
        Detection threshold at the sensor [dB_AE] (40 dB_AE = 100 uV).
    preamp_gain_db : float
        Gain between the sensor and the recorded volts [dB] (0: volts at the sensor).
    ddt_us : float
        Duration discrimination time (HDT) [us]: the hit ends after this long without a
        threshold crossing. 250 us bridges the gaps of a ringing hit (a plate's
        reverberation, a beating of modes) without merging hits a few ms apart.
    rearm_us : float
        Rearm time (HLT) [us] after the end of a hit during which no hit starts.
    pdt_us : float or None
        Peak definition time [us]: the peak is the first one not exceeded within this
        time (None: the largest peak of the hit, as Vallen).
    max_duration_us : float or None
        A hit longer than this is cut and the next one starts (None: no limit).
    floating_db : float or None
        Floating threshold: at least this many dB above each channel's noise rms (None:
        the fixed threshold only).
    onset_pre_us, onset_post_us : float
        The AIC onset window before and after the first crossing [us].
    """

    threshold_db_ae: float = 40.0
    preamp_gain_db: float = 0.0
    ddt_us: float = 250.0
    rearm_us: float = 0.0
    pdt_us: float | None = None
    max_duration_us: float | None = None
    floating_db: float | None = None
    onset_pre_us: float = 50.0
    onset_post_us: float = 20.0

    def __post_init__(self) -> None:
        for name, lo, opt in (("threshold_db_ae", -200.0, False), ("preamp_gain_db", -200.0,
                              False), ("ddt_us", 0.0, False), ("rearm_us", 0.0, False),
                              ("pdt_us", 0.0, True), ("max_duration_us", 0.0, True),
                              ("floating_db", 0.0, True), ("onset_pre_us", 0.0, False),
                              ("onset_post_us", 0.0, False)):
            object.__setattr__(self, name, _check(name, getattr(self, name), lo, opt))
        if self.threshold_db_ae > 200 or self.preamp_gain_db > 200:
            raise ValueError("threshold_db_ae and preamp_gain_db must be <= 200 dB")

    @property
    def gain(self) -> float:
        """Recorded volts per sensor volt."""
        return 10.0 ** (self.preamp_gain_db / 20.0)

    def threshold_v(self, noise_rms_v: float = 0.0) -> float:
        """The threshold in recorded volts (gain included), floating above the noise."""
        thr = db_ae_to_v(self.threshold_db_ae) * self.gain
        if self.floating_db is not None:
            thr = max(thr, float(noise_rms_v) * 10.0 ** (self.floating_db / 20.0))
        return thr


@dataclass
class Hit:
    """One hit on one channel: times on the file's clock, levels at the sensor.

    ``peak_v``, ``threshold_v`` and ``noise_rms_v`` are in recorded volts (gain
    included); ``amplitude_db_ae`` and the energies at the sensor. ``truncated``:
    'start' (the first crossing is within `NOISE_GUARD_SAMPLES` of the record's start: the
    hit may have begun before it), 'end' (within DDT of the record's end: it may go on past
    it) or ''.
    """

    channel: object
    record: int
    crossing_time_s: float
    onset_time_s: float
    peak_v: float
    amplitude_db_ae: float
    rise_time_s: float
    duration_s: float
    counts: int
    energy_v2s: float
    energy_eu: float
    threshold_v: float
    noise_rms_v: float
    snr_db: float
    crossing_index: int
    onset_index: int
    end_index: int
    truncated: str = ""


def noise_floor_v(rec: Recording) -> np.ndarray:
    """Noise rms of each channel [V]: of the pre-trigger samples of a transient record,
    else of the quietest stretches of the recording (the lowest `NOISE_QUIET_SHARE` of
    its `NOISE_BLOCK_S` blocks), so no warm-up period hides a hit.

    Parameters
    ----------
    rec : Recording

    Returns
    -------
    numpy.ndarray
        (n_channels,) [V].
    """
    x = rec.samples_v
    quiet = rec.pretrigger_samples - NOISE_GUARD_SAMPLES
    if quiet >= 16:
        return x[:, :quiet].std(axis=1)
    block = max(16, int(round(NOISE_BLOCK_S * rec.sample_rate_hz)))
    n_blocks = x.shape[1] // block
    if n_blocks < 2:
        return x.std(axis=1)
    b = x[:, : n_blocks * block].reshape(x.shape[0], n_blocks, block)
    rms = np.sort(b.std(axis=2), axis=1)
    keep = max(1, int(round(NOISE_QUIET_SHARE * n_blocks)))
    return np.median(rms[:, :keep], axis=1)


def _segments(idx: np.ndarray, ddt: int, rearm: int, max_dur: int | None) -> list[tuple]:
    """(first, last) crossing sample of each hit from the sorted crossing samples (at most
    `MAX_HITS_PER_CHANNEL`)."""
    if idx.size == 0:
        return []
    ends = np.flatnonzero(np.diff(idx) > ddt)  # a gap longer than DDT ends a hit
    out, arm = [], -1
    while len(out) < MAX_HITS_PER_CHANNEL:
        k = int(np.searchsorted(idx, arm))
        if k >= idx.size:
            return out
        start = int(idx[k])
        g = int(np.searchsorted(ends, k))
        j = int(ends[g]) if g < ends.size else idx.size - 1
        cut = max_dur is not None and idx[j] - start > max_dur
        if cut:  # the next hit starts at the next crossing
            j = int(np.searchsorted(idx, start + max_dur, side="right")) - 1
        out.append((start, int(idx[j])))
        arm = int(idx[j]) + 1 if cut else int(idx[j]) + ddt + rearm + 1
    return out


def _peak(a: np.ndarray, pdt: int | None) -> int:
    """Index of the peak within a hit's magnitudes (first not exceeded within pdt)."""
    if pdt is None:
        return int(np.argmax(a))
    rises = np.flatnonzero(np.diff(np.maximum.accumulate(a)) > 0) + 1
    rises = np.concatenate(([0], rises))
    late = np.flatnonzero(np.diff(rises) > pdt)
    return int(rises[late[0]] if late.size else rises[-1])


def _onsets(x: np.ndarray, starts, floors, pre: int, post: int) -> np.ndarray:
    """AIC onsets of the hits starting (first crossing) at ``starts``, each no earlier
    than its ``floors`` sample (the previous hit's end) and no later than its crossing."""
    starts = np.asarray(starts, np.int64)
    pre, post = min(pre, MAX_ONSET_SIDE_SAMPLES), min(post, MAX_ONSET_SIDE_SAMPLES)
    length = pre + post + 1
    if starts.size == 0 or length < 7:
        return starts
    first = starts - pre
    lo = np.clip(np.asarray(floors, np.int64) - first, 0, None)
    out = np.empty_like(starts)
    step = max(1, AIC_CHUNK_SAMPLES // length)
    for i in range(0, starts.size, step):
        f = first[i:i + step]
        cols = np.clip(f[:, None] + np.arange(length)[None, :], 0, x.size - 1)
        on, _ = aic_pick(x[cols][:, None, :], margin=2, start=lo[i:i + step])
        out[i:i + step] = np.minimum(f + on, starts[i:i + step])
    return out


def find_hits(rec: Recording, definition: HitDefinition | None = None, *, record: int = 0,
              noise_rms_v: np.ndarray | None = None) -> list[Hit]:
    """The hits of every channel of one recording, in time order.

    Parameters
    ----------
    rec : Recording
    definition : HitDefinition or None
        None: the defaults.
    record : int
        Index of ``rec`` among the file's records (kept in each Hit).
    noise_rms_v : numpy.ndarray or None
        (n_channels,) [V]; None: `noise_floor_v`.

    Returns
    -------
    list of Hit
    """
    d = definition or HitDefinition()
    noise = noise_floor_v(rec) if noise_rms_v is None else np.asarray(noise_rms_v, float)
    fs = rec.sample_rate_hz
    hits = []
    for ch in range(rec.n_channels):
        x = rec.samples_v[ch]
        thr = d.threshold_v(float(noise[ch]))
        segs = _segments(np.flatnonzero(np.abs(x) >= thr), _samples(d.ddt_us, fs),
                         _samples(d.rearm_us, fs), _samples(d.max_duration_us, fs))
        floors = [0] + [e + 1 for _, e in segs[:-1]]
        onsets = _onsets(x, [s for s, _ in segs], floors, _samples(d.onset_pre_us, fs),
                         _samples(d.onset_post_us, fs))
        for (s, e), on in zip(segs, onsets):
            hits.append(_hit(rec, ch, x, s, e, int(on), thr, float(noise[ch]), d, record))
    hits.sort(key=lambda h: (h.crossing_time_s, str(h.channel)))
    return hits


def _samples(us, fs: float) -> int | None:
    return None if us is None else int(round(float(us) * 1e-6 * fs))


def _hit(rec, ch, x, s, e, on, thr, noise, d: HitDefinition, record: int) -> Hit:
    fs, g = rec.sample_rate_hz, d.gain
    seg = x[s: e + 1]
    pk = s + _peak(np.abs(seg), _samples(d.pdt_us, fs))
    peak = float(abs(x[pk]))
    up = np.count_nonzero((seg[1:] >= thr) & (seg[:-1] < thr)) + int(seg[0] >= thr)
    energy = float(np.dot(seg, seg)) / fs / (g * g)
    trunc = "start" if s < NOISE_GUARD_SAMPLES else (
        "end" if e + _samples(d.ddt_us, fs) >= x.size else "")
    t0 = rec.start_time_s
    return Hit(
        channel=rec.channels[ch], record=record, crossing_time_s=t0 + s / fs,
        onset_time_s=t0 + on / fs, peak_v=peak, amplitude_db_ae=v_to_db_ae(peak / g),
        rise_time_s=(pk - s) / fs, duration_s=(e - s) / fs, counts=int(up),
        energy_v2s=energy, energy_eu=energy / EU_V2S, threshold_v=thr, noise_rms_v=noise,
        snr_db=20.0 * math.log10(peak / noise) if noise > 0 else math.inf,
        crossing_index=s, onset_index=on, end_index=e, truncated=trunc)


def threshold_warnings(rec: Recording, definition: HitDefinition,
                       noise_rms_v: np.ndarray) -> list[str]:
    """What makes the hits of a recording doubtful: a threshold within
    `MIN_THRESHOLD_NOISE_RATIO` of the noise (hits on noise), a clipped channel."""
    out = []
    for ch, name in enumerate(rec.channels):
        thr = definition.threshold_v(float(noise_rms_v[ch]))
        if thr < MIN_THRESHOLD_NOISE_RATIO * noise_rms_v[ch]:
            out.append(f"{rec.source}: channel {name}: threshold "
                       f"{v_to_db_ae(thr / definition.gain):.1f} dB_AE is within "
                       f"{20 * math.log10(MIN_THRESHOLD_NOISE_RATIO):.0f} dB of the noise "
                       f"({v_to_db_ae(noise_rms_v[ch] / definition.gain):.1f} dB_AE rms): "
                       "hits on noise; raise it or set a floating threshold")
    return out
