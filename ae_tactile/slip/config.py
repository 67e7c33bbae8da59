"""Parameters of the slip / texture detector, SI units, validated (clear ValueErrors).

See docs/slip.md for the reasoning behind every default. Lengths in metres, times in
seconds, rates in hertz.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace


def _num(name, value, *, lo=None, hi=None, lo_open=False, hi_open=False, allow_none=False):
    if value is None and allow_none:
        return None
    if isinstance(value, bool):
        raise ValueError(f"SlipConfig.{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"SlipConfig.{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"SlipConfig.{name} must be finite, got {value!r}")
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ValueError(f"SlipConfig.{name} must be {'>' if lo_open else '>='} {lo:g}, got {value!r}")
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise ValueError(f"SlipConfig.{name} must be {'<' if hi_open else '<='} {hi:g}, got {value!r}")
    return v


def _int(name, value, lo, hi):
    if isinstance(value, bool) or not hasattr(value, "__index__"):
        raise ValueError(f"SlipConfig.{name} must be an integer in [{lo}, {hi}], got {value!r}")
    v = int(value.__index__())
    if not lo <= v <= hi:
        raise ValueError(f"SlipConfig.{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return v


@dataclass(frozen=True)
class SlipConfig:
    """Slip / texture detector parameters (defaults: docs/slip.md, section "Parameters").

    Contact tracking
      association_radius_m   an emission belongs to a contact whose centre is closer than
                             this; must exceed 2 a_H of the largest expected contact, since a
                             contact that was never announced by a touch starts from one
                             emission on the edge of its micro-slip ring (5 mm: a_H <= 2.5 mm)
      release_gate_sigma     a rarefaction (polarity -1) releases an open touch when their
                             Mahalanobis distance under C_touch + C_release + floor^2 I is
                             below this
      release_floor_m        isotropic position uncertainty added to that gate (model error,
                             localization bias)
      release_confirm_s      a matched release ends its contact only if no slip emission
                             cancels it within this time (a centre emission of a slipping
                             contact looks like a release)
      max_contacts           contacts tracked per finger (the least recently active
                             non-slipping one is dropped beyond this)
      member_history         emissions kept per contact (bounded deque)
    Precursor (STICK -> INCIPIENT_SLIP, SLIP_PRECURSOR)
      evidence_window_s      micro-slip evidence is summed over this sliding window
      precursor_threshold    evidence needed: 1 per unmatched rarefaction near a contact
                             (no touch there can explain it), touch_evidence_weight per
                             unmatched compression near an existing contact (a new touch
                             until its release comes, a micro-slip if it never does)
      touch_evidence_weight  see above, in [0, 1]
      precursor_min_orphans  ... of which at least this many unmatched rarefactions (dense
                             touching alone, every touch later released where it began,
                             never fires)
    Rates and states
      rate_window_s          slip emission rate = count in this window / its length
      quiet_s                INCIPIENT_SLIP / GROSS_SLIP fall back to STICK after this
                             long without a slip emission
      gross_inner_fraction   gross slip: the stick zone is gone, emissions reach the
                             contact centre, closer than this fraction of the contact radius
      gross_window_events    ... counted among this many latest slip emissions
      gross_min_inner        ... at least this many of them
      gross_min_rate_hz      ... at a slip emission rate of at least this
      gross_min_events       ... once the contact's centre and radius rest on at least
                             this many emissions
      gross_exit_events      GROSS_SLIP -> INCIPIENT_SLIP when none of this many latest
                             slip emissions reached the centre (re-stuck centre)
    Texture (TEXTURE, spatial period = sliding speed / emission rate)
      texture_min_intervals  intervals between a contact's latest emissions tested
      texture_tolerance      an interval is regular when within this fraction of the
                             period of an integer multiple (1..texture_max_multiple,
                             multiples for missed packets) of the period
      texture_min_fraction   fraction of regular intervals needed (and of single ones:
                             texture_min_fraction - 0.15)
      texture_max_multiple   largest multiple of the period accepted for one interval
      texture_confirm_events a texture run starts after this many consecutive periodic
                             tests (one per emission; Poisson emissions pass one 16-interval
                             test with probability ~2e-5, two in a row ~3e-6, three: none in
                             3e5 windows)
      sliding_speed_m_s      sliding speed (None: unknown, spatial period NaN); settable
                             at run time (``SlipDetector.set_sliding_speed``)
    Direction of travel (SLIP / TEXTURE)
      direction_window_s     emission positions regressed on time over this window
      direction_min_events   at least this many emissions
      direction_min_speed_m_s  drift slower than this gives NaN
      direction_significance drift must exceed this many standard errors
    Overlaps
      overlap_guard_s        emissions closer in time than this to another one may share a
                             trigger window (the localizer does not catch every overlap and
                             then errs by up to ~1 mm with a small covariance): they count
                             for evidence and rates but not for the centre, the radius and
                             the gross-slip test
    Reporting
      report_interval_s      repeated SLIP_PRECURSOR / SLIP / TEXTURE events of one contact
                             are at least this far apart (the first one of a state is always
                             reported at once); 0: one per emission
      min_confidence         input events below this localization confidence are ignored
      reorder_tolerance_s    input events may be this much older than the newest one seen
                             (later ones are counted as rejected)
    """

    association_radius_m: float = 5e-3
    release_gate_sigma: float = 4.0
    release_floor_m: float = 0.05e-3
    release_confirm_s: float = 0.03
    max_contacts: int = 16
    member_history: int = 64
    evidence_window_s: float = 0.5
    precursor_threshold: float = 3.0
    touch_evidence_weight: float = 0.5
    precursor_min_orphans: int = 2
    rate_window_s: float = 0.1
    quiet_s: float = 0.3
    gross_inner_fraction: float = 0.4
    gross_window_events: int = 16
    gross_min_inner: int = 2
    gross_min_rate_hz: float = 20.0
    gross_exit_events: int = 40
    gross_min_events: int = 20
    texture_min_intervals: int = 16
    texture_tolerance: float = 0.2
    texture_min_fraction: float = 0.75
    texture_max_multiple: int = 3
    texture_confirm_events: int = 3
    sliding_speed_m_s: float | None = None
    direction_window_s: float = 0.2
    direction_min_events: int = 6
    direction_min_speed_m_s: float = 1e-3
    direction_significance: float = 3.0
    overlap_guard_s: float = 50e-6
    report_interval_s: float = 0.02
    min_confidence: float = 0.0
    reorder_tolerance_s: float = 1e-3

    def __post_init__(self):
        s = object.__setattr__
        s(self, "association_radius_m", _num("association_radius_m", self.association_radius_m, lo=0, lo_open=True, hi=0.05))
        s(self, "release_gate_sigma", _num("release_gate_sigma", self.release_gate_sigma, lo=0, lo_open=True))
        s(self, "release_floor_m", _num("release_floor_m", self.release_floor_m, lo=0, hi=0.01))
        s(self, "release_confirm_s", _num("release_confirm_s", self.release_confirm_s, lo=0, hi=10))
        s(self, "max_contacts", _int("max_contacts", self.max_contacts, 1, 1024))
        s(self, "member_history", _int("member_history", self.member_history, 8, 4096))
        s(self, "evidence_window_s", _num("evidence_window_s", self.evidence_window_s, lo=0, lo_open=True, hi=60))
        s(self, "precursor_threshold", _num("precursor_threshold", self.precursor_threshold, lo=0, lo_open=True, hi=1000))
        s(self, "touch_evidence_weight", _num("touch_evidence_weight", self.touch_evidence_weight, lo=0, hi=1))
        s(self, "precursor_min_orphans", _int("precursor_min_orphans", self.precursor_min_orphans, 0, 1000))
        s(self, "rate_window_s", _num("rate_window_s", self.rate_window_s, lo=0, lo_open=True, hi=60))
        s(self, "quiet_s", _num("quiet_s", self.quiet_s, lo=0, lo_open=True, hi=600))
        s(self, "gross_inner_fraction", _num("gross_inner_fraction", self.gross_inner_fraction, lo=0, lo_open=True, hi=1))
        s(self, "gross_window_events", _int("gross_window_events", self.gross_window_events, 1, 1000))
        s(self, "gross_min_inner", _int("gross_min_inner", self.gross_min_inner, 1, 1000))
        s(self, "gross_min_rate_hz", _num("gross_min_rate_hz", self.gross_min_rate_hz, lo=0))
        s(self, "gross_min_events", _int("gross_min_events", self.gross_min_events, 1, 4096))
        s(self, "gross_exit_events", _int("gross_exit_events", self.gross_exit_events, 1, 4096))
        s(self, "texture_min_intervals", _int("texture_min_intervals", self.texture_min_intervals, 3, 1000))
        s(self, "texture_tolerance", _num("texture_tolerance", self.texture_tolerance, lo=0, lo_open=True, hi=0.5, hi_open=True))
        s(self, "texture_min_fraction", _num("texture_min_fraction", self.texture_min_fraction, lo=0.5, hi=1))
        s(self, "texture_max_multiple", _int("texture_max_multiple", self.texture_max_multiple, 1, 10))
        s(self, "texture_confirm_events", _int("texture_confirm_events", self.texture_confirm_events, 1, 1000))
        s(self, "sliding_speed_m_s", _num("sliding_speed_m_s", self.sliding_speed_m_s, lo=0, lo_open=True, hi=100,
                                          allow_none=True))
        s(self, "direction_window_s", _num("direction_window_s", self.direction_window_s, lo=0, lo_open=True, hi=60))
        s(self, "direction_min_events", _int("direction_min_events", self.direction_min_events, 3, 4096))
        s(self, "direction_min_speed_m_s", _num("direction_min_speed_m_s", self.direction_min_speed_m_s, lo=0))
        s(self, "direction_significance", _num("direction_significance", self.direction_significance, lo=0))
        s(self, "overlap_guard_s", _num("overlap_guard_s", self.overlap_guard_s, lo=0, hi=1))
        s(self, "report_interval_s", _num("report_interval_s", self.report_interval_s, lo=0, hi=60))
        s(self, "min_confidence", _num("min_confidence", self.min_confidence, lo=0, hi=1))
        s(self, "reorder_tolerance_s", _num("reorder_tolerance_s", self.reorder_tolerance_s, lo=0, hi=60))
        if self.gross_min_inner > self.gross_window_events:
            raise ValueError(f"SlipConfig.gross_min_inner ({self.gross_min_inner}) must not exceed "
                             f"gross_window_events ({self.gross_window_events})")
        need = max(self.gross_window_events, self.gross_exit_events, self.gross_min_events, self.texture_min_intervals + 1)
        if need > self.member_history:
            raise ValueError(f"SlipConfig.member_history ({self.member_history}) must hold gross_window_events, "
                             f"gross_exit_events and texture_min_intervals + 1 emissions ({need})")

    def replace(self, **changes) -> "SlipConfig":
        return replace(self, **changes)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))
