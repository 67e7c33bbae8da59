# SPDX-License-Identifier: Apache-2.0
"""Recorded AE data in: WAV, Vallen pridb/tradb, CSV and NPY/NPZ files as `Recording` s.

Every reader returns a list of `Recording` (one for a continuous file, one per transient
record for a Vallen tradb): samples in volts as (n_channels, N) float64, the sample rate,
the pre-trigger length, the time of the first sample and the channel names, taken from
the file's own metadata where the format has them:

- WAV (scipy.io.wavfile, any channel count): float samples are volts as stored; integer
  PCM is scaled so that the format's full scale is ``full_scale_v`` (default 1.0 V, said
  in the recording's notes because a WAV file does not know its volts);
- Vallen tradb (through `vallenae`, an optional dependency): each transient record, in
  volts with its pre-trigger, sample rate, threshold and hit time; `read_vallen_hits`
  gives the pridb's hits with their hardware arrival times;
- CSV: one column per channel in volts, and a time column (``time``, ``t``, ``time_s``...)
  or a sample rate given by the caller;
- NPY: a 2-D array (channels, N) or (N, channels) (the shorter axis is the channels) or
  1-D, with the sample rate given; NPZ: ``samples_v`` (volts) or ``samples`` (times
  ``lsb_v`` if stored, as `ae_tactile.sim.cli` writes them) with ``sample_rate_hz`` and
  optionally ``pretrigger_samples``, ``start_time_s`` / ``start_time_ns``, ``channels``.

A file that cannot be read raises `RecordingError` (a ValueError) naming the file and
what is wrong with it.
"""

from __future__ import annotations

import csv
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.io import wavfile

#: file suffix -> format name
SUFFIX_FORMATS = {
    ".wav": "wav", ".wave": "wav", ".pridb": "vallen", ".tradb": "vallen",
    ".csv": "csv", ".txt": "csv", ".tsv": "csv", ".npy": "npy", ".npz": "npy",
}
FORMATS = ("wav", "vallen", "csv", "npy")
#: CSV header names taken as the time column [s]
TIME_COLUMNS = ("time", "t", "time_s", "time[s]", "time (s)", "time [s]", "seconds")
#: sample rates accepted [Hz]: below, no AE; above, no real digitiser
SAMPLE_RATE_RANGE_HZ = (1e3, 1e10)


class RecordingError(ValueError):
    """A recording that cannot be read: the message names the file and the problem."""


@dataclass
class Recording:
    """One stretch of recorded samples, in volts.

    Attributes
    ----------
    samples_v : numpy.ndarray
        (n_channels, N) float64 [V] as recorded (preamplifier gain included).
    sample_rate_hz : float
        Sample rate [Hz].
    pretrigger_samples : int
        Samples before the acquisition's trigger (0: a continuous recording).
    start_time_s : float
        Time of ``samples_v[:, 0]`` on the file's clock [s].
    channels : tuple
        One name or number per row of ``samples_v``.
    source : str
        The file it came from.
    threshold_v : float or None
        The acquisition's own trigger threshold [V] where the file stores it (Vallen).
    notes : tuple of str
        What the reader assumed (e.g. the full scale of integer PCM).
    """

    samples_v: np.ndarray
    sample_rate_hz: float
    pretrigger_samples: int = 0
    start_time_s: float = 0.0
    channels: tuple = ()
    source: str = ""
    threshold_v: float | None = None
    notes: tuple = ()

    def __post_init__(self) -> None:
        where = self.source or "recording"
        x = np.asarray(self.samples_v, dtype=np.float64)
        if x.ndim == 1:
            x = x[None, :]
        if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 2:
            raise RecordingError(f"{where}: samples must be (n_channels, N >= 2), got "
                                 f"shape {np.shape(self.samples_v)}")
        if not np.isfinite(x).all():
            raise RecordingError(f"{where}: {int((~np.isfinite(x)).sum())} samples are NaN "
                                 "or infinite")
        self.samples_v = x
        self.sample_rate_hz = check_sample_rate(self.sample_rate_hz, where)
        self.pretrigger_samples = int(min(max(int(self.pretrigger_samples), 0), x.shape[1]))
        self.start_time_s = float(self.start_time_s)
        if not math.isfinite(self.start_time_s):
            raise RecordingError(f"{where}: start time {self.start_time_s!r} is not finite")
        if not self.channels:
            self.channels = tuple(range(x.shape[0]))
        self.channels = tuple(self.channels)
        if len(self.channels) != x.shape[0]:
            raise RecordingError(f"{where}: {len(self.channels)} channel names for "
                                 f"{x.shape[0]} channels")
        self.notes = tuple(self.notes)

    @property
    def n_channels(self) -> int:
        return int(self.samples_v.shape[0])

    @property
    def n_samples(self) -> int:
        return int(self.samples_v.shape[1])

    @property
    def duration_s(self) -> float:
        return self.n_samples / self.sample_rate_hz


def check_sample_rate(sample_rate_hz, where: str = "recording") -> float:
    """The sample rate as a float [Hz], or a RecordingError saying why it is unusable."""
    try:
        fs = float(sample_rate_hz)
    except (TypeError, ValueError):
        raise RecordingError(f"{where}: sample rate {sample_rate_hz!r} is not a number") from None
    lo, hi = SAMPLE_RATE_RANGE_HZ
    if not (math.isfinite(fs) and lo <= fs <= hi):
        raise RecordingError(f"{where}: sample rate {sample_rate_hz!r} Hz is outside "
                             f"{lo:g} .. {hi:g} Hz")
    return fs


def detect_format(path) -> str:
    """Format name of a file from its suffix (`SUFFIX_FORMATS`)."""
    fmt = SUFFIX_FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise RecordingError(f"{path}: unknown recording format (suffix "
                             f"{Path(path).suffix!r}); give one of {', '.join(FORMATS)}")
    return fmt


def read_recording(path, *, format: str | None = None, sample_rate_hz: float | None = None,
                   full_scale_v: float | None = None) -> list[Recording]:
    """Read a recording file into volts.

    Parameters
    ----------
    path : str or os.PathLike
        The file (a Vallen .pridb is read through the .tradb beside it).
    format : {'wav', 'vallen', 'csv', 'npy'} or None
        None: from the suffix (`detect_format`).
    sample_rate_hz : float or None
        [Hz] for formats that do not store it (CSV without a time column, NPY, an NPZ
        without ``sample_rate_hz``); a file that stores its own rate wins over it.
    full_scale_v : float or None
        [V] of integer PCM full scale in a WAV file (None: 1.0 V, said in the notes).

    Returns
    -------
    list of Recording
        One per continuous file, one per transient record (Vallen).

    Raises
    ------
    RecordingError
        The file is missing, of an unknown format, or its content is unusable.
    """
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{path}: no such file")
    fmt = (format or detect_format(p)).lower()
    if fmt == "wav":
        return [read_wav(p, full_scale_v=full_scale_v)]
    if fmt == "vallen":
        return read_vallen_tradb(p)
    if fmt == "csv":
        return [read_csv(p, sample_rate_hz=sample_rate_hz)]
    if fmt == "npy":
        return [read_numpy(p, sample_rate_hz=sample_rate_hz)]
    raise RecordingError(f"{path}: unknown format {format!r}; give one of {', '.join(FORMATS)}")


def read_wav(path, *, full_scale_v: float | None = None) -> Recording:
    """A WAV file: float samples as volts, integer PCM scaled to ``full_scale_v`` [V].

    Parameters
    ----------
    path : str or os.PathLike
        The .wav file (any channel count; 8, 16, 24, 32-bit PCM or float).
    full_scale_v : float or None
        Volts at the PCM full scale (None: 1.0 V, noted).

    Returns
    -------
    Recording
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", wavfile.WavFileWarning)  # unknown chunks
            rate, data = wavfile.read(str(path))
    except (ValueError, OSError, EOFError) as exc:
        raise RecordingError(f"{path}: not a readable WAV file ({exc})") from None
    x = np.asarray(data)
    x = x[:, None] if x.ndim == 1 else x
    notes = []
    if np.issubdtype(x.dtype, np.integer):
        fs_v = 1.0 if full_scale_v is None else float(full_scale_v)
        if not (math.isfinite(fs_v) and fs_v > 0):
            raise RecordingError(f"{path}: full_scale_v must be > 0, got {full_scale_v!r}")
        if x.dtype == np.uint8:  # 8-bit WAV is offset binary
            volts = (x.astype(np.float64) - 128.0) * (fs_v / 128.0)
        else:
            volts = x.astype(np.float64) * (fs_v / float(-np.iinfo(x.dtype).min))
        how = "given" if full_scale_v is not None else "default: give the ADC's full scale"
        notes.append(f"integer PCM ({x.dtype}) scaled to full scale {fs_v:g} V ({how})")
    else:
        volts = x.astype(np.float64)
        notes.append("float WAV samples taken as volts")
    return Recording(volts.T, rate, source=str(path), notes=tuple(notes))


def read_csv(path, *, sample_rate_hz: float | None = None) -> Recording:
    """A CSV file: a header row (optional), a time column (optional), one column per
    channel in volts; the delimiter (comma, semicolon, tab, spaces) is detected.

    Parameters
    ----------
    path : str or os.PathLike
        The file.
    sample_rate_hz : float or None
        [Hz], needed when the file has no time column.

    Returns
    -------
    Recording
    """
    text = _read_text(path)
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2:
        raise RecordingError(f"{path}: fewer than 2 data rows")
    rows = _split_rows(lines, path)
    header = None
    if not _is_numeric_row(rows[0]):
        header, rows = [h.strip().lower() for h in rows[0]], rows[1:]
    if len(rows) < 2:
        raise RecordingError(f"{path}: fewer than 2 data rows")
    bad = next((i for i, r in enumerate(rows) if not _is_numeric_row(r)), None)
    if bad is not None:
        raise RecordingError(f"{path}: row {bad + 1 + (header is not None)} is not numeric: "
                             f"{','.join(rows[bad])[:80]!r}")
    widths = {len(r) for r in rows} | ({len(header)} if header is not None else set())
    if len(widths) > 1:
        raise RecordingError(f"{path}: rows have different numbers of columns "
                             f"({', '.join(map(str, sorted(widths)))})")
    data = np.array([[float(v) for v in r] for r in rows], dtype=np.float64)
    names = header or [f"ch{i}" for i in range(data.shape[1])]
    t_col = next((i for i, h in enumerate(names) if h in TIME_COLUMNS), None)
    notes = []
    if t_col is not None:
        fs, t0 = _rate_from_times(data[:, t_col], path)
        if sample_rate_hz is not None and not math.isclose(fs, float(sample_rate_hz),
                                                           rel_tol=1e-3):
            notes.append(f"time column's {fs:g} Hz used, not the {float(sample_rate_hz):g} Hz "
                         "given")
        keep = [i for i in range(data.shape[1]) if i != t_col]
    else:
        if sample_rate_hz is None:
            raise RecordingError(f"{path}: no time column ({', '.join(TIME_COLUMNS[:3])}...) "
                                 "and no sample rate given")
        fs, t0, keep = sample_rate_hz, 0.0, list(range(data.shape[1]))
    if not keep:
        raise RecordingError(f"{path}: no channel column beside the time column")
    return Recording(data[:, keep].T, fs, start_time_s=t0,
                     channels=tuple(names[i] for i in keep), source=str(path),
                     notes=tuple(notes + ["CSV values taken as volts"]))


def _read_text(path) -> str:
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read ({exc.strerror})") from None
    if b"\0" in raw[:4096]:
        raise RecordingError(f"{path}: binary content, not a CSV text file")
    return raw.decode("utf-8-sig", errors="replace")


def _split_rows(lines: list[str], path) -> list[list[str]]:
    sample = "\n".join(lines[:20])
    try:
        dialect = csv.Sniffer().sniff(sample, delimiters=",;\t ")
        delim = dialect.delimiter
    except csv.Error:
        delim = ","
    if delim == " ":
        return [ln.split() for ln in lines]
    return [[v.strip() for v in r] for r in csv.reader(lines, delimiter=delim)]


def _is_numeric_row(row) -> bool:
    try:
        [float(v) for v in row]
    except ValueError:
        return False
    return bool(row)


def _rate_from_times(t: np.ndarray, path) -> tuple[float, float]:
    """(sample rate [Hz], first time [s]) of a time column, which must be uniform."""
    dt = np.diff(t)
    if not np.isfinite(t).all() or np.any(dt <= 0):
        raise RecordingError(f"{path}: the time column is not strictly increasing")
    step = float(np.median(dt))
    if np.max(np.abs(dt - step)) > 0.01 * step:
        raise RecordingError(f"{path}: the time column is not uniformly sampled (steps "
                             f"{dt.min():.3g} .. {dt.max():.3g} s)")
    span = float(t[-1] - t[0])
    return (len(t) - 1) / span, float(t[0])


def read_numpy(path, *, sample_rate_hz: float | None = None) -> Recording:
    """An NPY array or an NPZ archive (see the module docstring for the keys).

    Parameters
    ----------
    path : str or os.PathLike
        The .npy or .npz file.
    sample_rate_hz : float or None
        [Hz] when the file does not store ``sample_rate_hz``.

    Returns
    -------
    Recording
    """
    try:
        obj = np.load(str(path), allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise RecordingError(f"{path}: not a readable NPY/NPZ file ({exc})") from None
    if isinstance(obj, np.ndarray):
        return _from_array(obj, sample_rate_hz, path, {})
    with obj:
        meta = {k: obj[k] for k in obj.files}
    key = next((k for k in ("samples_v", "samples") if k in meta), None)
    if key is None:
        arrays = [k for k, v in meta.items() if v.ndim in (1, 2) and v.size > 1]
        if len(arrays) != 1:
            raise RecordingError(f"{path}: no 'samples_v' or 'samples' array (holds "
                                 f"{', '.join(sorted(meta)) or 'nothing'})")
        key = arrays[0]
    x = meta[key]
    if key == "samples" and "lsb_v" in meta:
        x = x.astype(np.float64) * float(meta["lsb_v"])
    return _from_array(x, sample_rate_hz, path, meta)


def _from_array(x: np.ndarray, sample_rate_hz, path, meta: dict) -> Recording:
    if not (np.issubdtype(x.dtype, np.number) and x.ndim in (1, 2)):
        raise RecordingError(f"{path}: samples must be a 1-D or 2-D numeric array, got "
                             f"{x.dtype} {x.shape}")
    x = np.asarray(x, dtype=np.float64)
    x = x[None, :] if x.ndim == 1 else x
    if x.shape[0] > x.shape[1]:  # (N, channels): the shorter axis holds the channels
        x = x.T
    fs = meta.get("sample_rate_hz", sample_rate_hz)
    if fs is None:
        raise RecordingError(f"{path}: no sample rate stored ('sample_rate_hz') and none "
                             "given")
    start = float(meta["start_time_s"]) if "start_time_s" in meta else (
        int(meta["start_time_ns"]) * 1e-9 if "start_time_ns" in meta else 0.0)
    names = tuple(meta["channels"].tolist()) if "channels" in meta else ()
    fs = check_sample_rate(fs.item() if isinstance(fs, np.ndarray) else fs, str(path))
    return Recording(x, fs, int(meta.get("pretrigger_samples", 0)), start, names, str(path))


def _vallenae(path):
    try:
        import vallenae  # lazy: optional dependency (the 'recordings' extra)
    except ImportError:
        raise RecordingError(f"{path}: reading Vallen files needs the optional package "
                             "vallenae (pip install vallenae, or the 'recordings' "
                             "extra)") from None
    return vallenae


def _sibling(path: Path, suffix: str) -> Path:
    other = path.with_suffix(suffix)
    if not other.is_file():
        raise RecordingError(f"{path}: no {suffix} file beside it ({other.name} missing)")
    return other


def read_vallen_tradb(path) -> list[Recording]:
    """Every transient record of a Vallen tradb (or of the tradb beside a pridb).

    Parameters
    ----------
    path : str or os.PathLike
        A .tradb, or a .pridb with its .tradb beside it.

    Returns
    -------
    list of Recording
        One per record (one channel each), in volts with its pre-trigger; the start time
        is the record's hit time minus the pre-trigger; ``threshold_v`` is the
        acquisition's threshold.
    """
    vae = _vallenae(path)
    p = Path(path)
    tra = _sibling(p, ".tradb") if p.suffix.lower() == ".pridb" else p
    out = []
    try:
        with vae.io.TraDatabase(str(tra)) as db:
            for r in db.iread():
                fs = float(r.samplerate)
                out.append(Recording(
                    np.asarray(r.data, dtype=np.float64), fs, int(r.pretrigger),
                    float(r.time) - int(r.pretrigger) / fs, (int(r.channel),), str(tra),
                    threshold_v=float(r.threshold) if r.threshold else None,
                    notes=(f"Vallen TRAI {int(r.trai)}",)))
    except RecordingError:
        raise
    except Exception as exc:  # noqa: BLE001 - sqlite3 / vallenae errors on a bad file
        raise RecordingError(f"{tra}: not a readable Vallen tradb ({exc})") from None
    if not out:
        raise RecordingError(f"{tra}: holds no transient records")
    return out


@dataclass(frozen=True)
class VallenHit:
    """One hit of a Vallen pridb, as the acquisition measured it (volts at the sensor)."""

    time_s: float  # hardware arrival time: first threshold crossing [s]
    channel: int
    amplitude_v: float
    threshold_v: float
    duration_s: float
    rise_time_s: float
    counts: int
    energy_eu: float  # [eu] = 1e-14 V^2 s
    trai: int  # transient record index (0: none)


def read_vallen_hits(path) -> list[VallenHit]:
    """The hits of a Vallen pridb (or of the pridb beside a tradb), in time order.

    Parameters
    ----------
    path : str or os.PathLike
        A .pridb, or a .tradb with its .pridb beside it.

    Returns
    -------
    list of VallenHit
    """
    vae = _vallenae(path)
    p = Path(path)
    pri = _sibling(p, ".pridb") if p.suffix.lower() == ".tradb" else p

    def num(v, default=0.0):
        return default if v is None or v != v else v

    try:
        with vae.io.PriDatabase(str(pri)) as db:
            hits = [VallenHit(float(h.time), int(h.channel), float(h.amplitude),
                              float(num(h.threshold)), float(num(h.duration)),
                              float(num(h.rise_time)), int(num(h.counts, 0)),
                              float(num(h.energy)), int(num(h.trai, 0)))
                    for h in db.iread_hits()]
    except Exception as exc:  # noqa: BLE001 - sqlite3 / vallenae errors on a bad file
        raise RecordingError(f"{pri}: not a readable Vallen pridb ({exc})") from None
    return sorted(hits, key=lambda h: (h.time_s, h.channel))
