# SPDX-License-Identifier: Apache-2.0
"""Parameters of the slip / texture detector, SI units, validated (clear ValueErrors).

Every field carries its description, unit, valid range and whether it may change at run
time in the dataclass field metadata (``doc``, ``unit``, ``lo``, ``hi``, ``runtime``):
``SlipConfig.describe()`` returns them, so the ROS layer can generate parameter
descriptors from one place. See docs/slip.md for the reasoning behind every default.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import asdict, dataclass, field, fields, replace

from ae_tactile.localization.weak_release import RELEASE_FLOOR_M, RELEASE_GATE_SIGMA


def _p(
    default,
    doc,
    unit="",
    lo=None,
    hi=None,
    *,
    kind="float",
    lo_open=False,
    runtime=True,
    allow_none=False,
):
    return field(
        default=default,
        metadata={
            "doc": doc,
            "unit": unit,
            "lo": lo,
            "hi": hi,
            "kind": kind,
            "lo_open": lo_open,
            "runtime": runtime,
            "allow_none": allow_none,
        },
    )


def _check(name, md, value):
    if value is None and md["allow_none"]:
        return None
    lo, hi = md["lo"], md["hi"]
    if md["kind"] == "int":
        if isinstance(value, bool) or not hasattr(value, "__index__"):
            raise ValueError(
                f"SlipConfig.{name} must be an integer in [{lo}, {hi}], got {value!r}"
            )
        v = int(value.__index__())
        if not lo <= v <= hi:
            raise ValueError(
                f"SlipConfig.{name} must be an integer in [{lo}, {hi}], got {value!r}"
            )
        return v
    if isinstance(value, bool):
        raise ValueError(f"SlipConfig.{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"SlipConfig.{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"SlipConfig.{name} must be finite, got {value!r}")
    if lo is not None and (v < lo or (md["lo_open"] and v == lo)):
        raise ValueError(
            f"SlipConfig.{name} must be {'>' if md['lo_open'] else '>='} {lo:g}, got {value!r}"
        )
    if hi is not None and v > hi:
        raise ValueError(f"SlipConfig.{name} must be <= {hi:g}, got {value!r}")
    return v


@dataclass(frozen=True)
class SlipConfig:
    """Slip / texture detector parameters, SI units, validated on construction.

    Every field carries its description, unit, valid range and whether it may change at
    run time in its metadata (``describe()``); the parameter list below is generated from
    it (docs/slip.md, section "Parameters", gives the reasoning behind the defaults).
    """

    # ------------------------------------------------------------------ tracking
    association_radius_m: float = _p(
        5e-3,
        "an emission belongs to the contact whose (predicted) centre is closer than this; "
        "more than the diameter of the largest Hertz contact (2 a_H <= 5 mm)",
        "m",
        0.0,
        0.05,
        lo_open=True,
    )
    release_gate_sigma: float = _p(
        RELEASE_GATE_SIGMA,
        "two emissions of a contact are one spot (a touch and its release, repeated taps) "
        "when their distance is below this many standard deviations of the difference",
        "",
        0.0,
        100.0,
        lo_open=True,
    )
    release_floor_m: float = _p(
        RELEASE_FLOOR_M,
        "isotropic position uncertainty added to that gate (model error, bias)",
        "m",
        0.0,
        0.01,
    )
    release_confirm_s: float = _p(
        0.03,
        "an emission on the founding touch's spot ends a held contact after this time unless "
        "the contact slips meanwhile",
        "s",
        0.0,
        10.0,
    )
    max_contacts: int = _p(
        16,
        "contacts tracked per finger (the least recently active one is dropped)",
        "",
        1,
        1024,
        kind="int",
        runtime=False,
    )
    member_history: int = _p(
        64, "emissions kept per contact (ring buffer)", "", 16, 4096, kind="int", runtime=False
    )
    track_window_s: float = _p(
        0.5,
        "the contact's motion (centre and velocity along the surface) is regressed on its "
        "emissions in this window",
        "s",
        0.0,
        60.0,
        lo_open=True,
    )
    track_min_events: int = _p(
        6, "motion regression needs at least this many emissions", "", 3, 4096, kind="int"
    )
    track_significance: float = _p(
        5.0, "a contact moves when its speed exceeds this many standard errors", "", 0.0, 100.0
    )
    track_max_residual_m: float = _p(
        0.6e-3,
        "... and when its emissions stay this close (rms per axis) to the fitted track",
        "m",
        0.0,
        0.05,
        lo_open=True,
    )
    direction_significance: float = _p(
        4.0,
        "a SLIP of a contact not (yet) tracked as moving reports the direction of its "
        "emissions' drift when that exceeds this many standard errors",
        "",
        0.0,
        100.0,
    )
    min_speed_m_s: float = _p(1e-3, "slower drift is no motion (direction NaN)", "m/s", 0.0, 10.0)
    # ------------------------------------------------------------------ precursor
    evidence_window_s: float = _p(
        2.0,
        "micro-slip evidence of a contact is counted over this sliding window",
        "s",
        0.0,
        60.0,
        lo_open=True,
    )
    precursor_min_emissions: int = _p(
        2,
        "SLIP_PRECURSOR when this many micro-slip emissions (isolated: on no other emission's "
        "spot, e.g. not a touch's release or a repeated tap) besides the founding one fall in the "
        "contact within the window",
        "",
        1,
        1000,
        kind="int",
    )
    compression_evidence_weight: float = _p(
        1.0,
        "weight of a compression (polarity +1) as micro-slip evidence; 1: polarity-free (any "
        "polarity mix of micro-slips is detected alike); < 1: a new touch next to a held one "
        "whose release the localizer lost counts less (fewer false precursors in dense "
        "touching, later precursors for compressive micro-slips)",
        "",
        0.0,
        1.0,
    )
    touched_compression_weight: float = _p(
        0.0,
        "weight of a compression as micro-slip evidence in a contact for evidence_window_s "
        "after a touch's release (a rarefaction on a compression's spot, in the contact or in "
        "one that ended within association_radius_m), and until the contact's next "
        "compression however late (a compression that came then keeps this weight): "
        "objects touch and leave there, and an unpaired compression is a touch whose "
        "release is still to come or was lost rather than a micro-slip (rarefactions still "
        "count)",
        "",
        0.0,
        1.0,
    )
    rate_window_s: float = _p(
        0.1, "slip emission rate = count in this window / its length", "s", 0.0, 60.0, lo_open=True
    )
    quiet_s: float = _p(
        0.3,
        "INCIPIENT_SLIP / GROSS_SLIP fall back to STICK after this long without "
        "an emission of the contact",
        "s",
        0.0,
        600.0,
        lo_open=True,
    )
    fit_min_events: int = _p(
        4,
        "the contact's centre is fitted (circle through its micro-slips: they ring the stick "
        "zone) once this many are known; before, the founding emission",
        "",
        3,
        1000,
        kind="int",
    )
    # ------------------------------------------------------------------ gross slip
    gross_window_s: float = _p(
        0.04,
        "gross-slip tests look at the contact's emissions in this latest window",
        "s",
        0.0,
        10.0,
        lo_open=True,
    )
    gross_min_events: int = _p(
        3,
        "... at least this many emissions in it (a rate of at least "
        "gross_min_events / gross_window_s)",
        "",
        2,
        1000,
        kind="int",
    )
    gross_inner_fraction: float = _p(
        0.35,
        "gross slip: an emission of the window lies closer to the centre than this fraction of "
        "the contact radius (no stick zone left)",
        "",
        0.0,
        1.0,
        lo_open=True,
    )
    gross_rate_alpha: float = _p(
        1e-5,
        "... or the latest emissions came so fast that the contact's prior rate (learnt "
        "from its emissions over the preceding gross_history_s, Gamma(n + 1, time covered) "
        "x gross_rate_growth) explains them with a probability below this "
        "(a jump of the emission rate; scanned over the latest gross_min_events .. "
        "gross_scan_events emissions)",
        "",
        0.0,
        0.5,
        lo_open=True,
    )
    gross_scan_events: int = _p(8, "see gross_rate_alpha", "", 2, 64, kind="int")
    gross_history_s: float = _p(0.5, "see gross_rate_alpha", "s", 0.0, 60.0, lo_open=True)
    gross_llr_threshold: float = _p(
        7.0,
        "gross slip (tested first) when the log likelihood ratio of the latest "
        "gross_min_events .. gross_scan_events emissions, gross slip (Poisson at a rate in "
        "gross_rate_min_hz .. gross_rate_max_hz, uniform over the contact disc) against "
        "micro-slip continuation (Poisson at the contact's own prior rate x "
        "gross_rate_growth, in the slip annulus), reaches this; 0 disables it",
        "",
        0.0,
        1000.0,
    )
    gross_rate_min_hz: float = _p(
        100.0,
        "lowest gross-slip emission rate of that test's gross-slip hypothesis (the fitted "
        "rate is clipped into gross_rate_min_hz .. gross_rate_max_hz)",
        "1/s",
        0.0,
        1e6,
        lo_open=True,
    )
    gross_rate_max_hz: float = _p(
        1000.0,
        "highest gross-slip emission rate of that hypothesis",
        "1/s",
        0.0,
        1e6,
        lo_open=True,
    )
    gross_prior_s: float = _p(
        1.0,
        "the micro-slip hypothesis' rate is learnt from the contact's emissions over this "
        "much of its life before the tested ones (Gamma(n + 1, time covered))",
        "s",
        0.0,
        60.0,
        lo_open=True,
    )
    gross_rate_growth: float = _p(
        1.5,
        "... times this: the Cattaneo-Mindlin micro-slip rate grows as (1 - q)^(-1/3) "
        "toward gross slip (at q = 0.9 about 1.6 times its average since q = 0)",
        "",
        1.0,
        1000.0,
    )
    gross_stick_fraction: float = _p(
        0.45,
        "the micro-slip hypothesis' emissions lie outside this fraction of the radius of the "
        "ring fitted before the tested ones (the stick zone c = a_H (1 - q)^(1/3) left at "
        "q = 1 - fraction^3: 0.45 at q = 0.91), half of them outside the innermost "
        "micro-slip seen; gross slip's anywhere in the disc (uniform by area)",
        "",
        0.0,
        1.0,
    )
    gross_position_outlier: float = _p(
        0.03,
        "share of the micro-slip hypothesis' emissions anywhere in the disc (fit and "
        "localization errors): an emission inside the stick zone weighs ln(1/this)",
        "",
        0.0,
        1.0,
        lo_open=True,
    )
    # ------------------------------------------------------------------ texture
    texture_min_intervals: int = _p(
        16,
        "intervals between the contact's latest emissions tested for periodicity",
        "",
        4,
        1000,
        kind="int",
    )
    texture_interval_sd: float = _p(
        0.3,
        "standard deviation of one interval of a texture, as a fraction of the period (a "
        "timing jitter sigma of the emissions gives sqrt(2) sigma)",
        "",
        0.0,
        1.0,
        lo_open=True,
    )
    texture_min_llr: float = _p(
        9.0,
        "periodic when the log-likelihood ratio of the intervals, jittered periodic (with "
        "missed packets) against Poisson, is at least this (Poisson: above 9 in ~5e-5 of "
        "16-interval windows; 20 % jitter: ~85 %)",
        "",
        0.0,
        1000.0,
    )
    texture_max_multiple: int = _p(
        3,
        "largest multiple of the period accepted for one interval (missed packets)",
        "",
        1,
        10,
        kind="int",
    )
    texture_confirm_events: int = _p(
        2,
        "a texture run starts after this many consecutive periodic tests",
        "",
        1,
        1000,
        kind="int",
    )
    texture_period_rel_se: float = _p(
        0.015,
        "a moving contact's spatial period (tracked speed x period) is reported once its "
        "relative standard error is below this",
        "",
        0.0,
        1.0,
        lo_open=True,
    )
    sliding_speed_m_s: float | None = _p(
        None,
        "sliding speed of a fixed contact over a texture (spatial period = v T); None: "
        "unknown (NaN) unless the contact is tracked moving",
        "m/s",
        0.0,
        100.0,
        lo_open=True,
        allow_none=True,
    )
    # ------------------------------------------------------------------ misc
    overlap_guard_s: float = _p(
        50e-6,
        "emissions closer in time than this may share a trigger window: "
        "they do not shape the contact's centre",
        "s",
        0.0,
        1.0,
    )
    report_interval_s: float = _p(
        0.02,
        "repeated events of one kind and contact are at least this "
        "far apart (the first one of a state is reported at once)",
        "s",
        0.0,
        60.0,
    )
    min_confidence: float = _p(
        0.0, "events below this localization confidence are rejected", "", 0.0, 1.0
    )
    reorder_tolerance_s: float = _p(
        0.5,
        "events may arrive this much older than the newest one seen (processed normally); "
        "older ones are rejected and counted (the emissions of an overlapping window are "
        "resolved in the background and arrive tens of ms after newer ones)",
        "s",
        0.0,
        60.0,
    )

    def __post_init__(self):
        for f in fields(self):
            object.__setattr__(self, f.name, _check(f.name, f.metadata, getattr(self, f.name)))
        if self.gross_rate_min_hz > self.gross_rate_max_hz:
            raise ValueError(
                f"SlipConfig.gross_rate_min_hz ({self.gross_rate_min_hz:g}) must not exceed "
                f"gross_rate_max_hz ({self.gross_rate_max_hz:g})"
            )
        if self.texture_min_intervals + 1 > self.member_history:
            raise ValueError(
                f"SlipConfig.member_history ({self.member_history}) must hold "
                f"texture_min_intervals + 1 emissions ({self.texture_min_intervals + 1})"
            )

    def replace(self, **changes) -> "SlipConfig":
        """A copy with ``changes`` (field -> value) applied.

        Returns
        -------
        SlipConfig
            The new configuration, validated (ValueError as on construction).
        """
        return replace(self, **changes)

    def as_dict(self) -> dict:
        """Returns
        -------
        dict
            field name -> value.
        """
        return asdict(self)

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """Returns
        -------
        tuple of str
            The field names, in declaration order.
        """
        return tuple(f.name for f in fields(cls))

    @classmethod
    def describe(cls) -> dict[str, dict]:
        """name -> {default, doc, unit, lo, hi, kind, runtime} for every field."""
        return {
            f.name: {
                "default": f.default,
                **{k: f.metadata[k] for k in ("doc", "unit", "lo", "hi", "kind", "runtime")},
            }
            for f in fields(cls)
        }

    @classmethod
    def runtime_fields(cls) -> tuple[str, ...]:
        """Fields that ``SlipDetector.update_config`` may change while running."""
        return tuple(f.name for f in fields(cls) if f.metadata["runtime"])


def _field_list_doc() -> str:
    """The numpydoc Parameters and Raises sections of the class docstring, generated from
    the field metadata so they cannot drift: per field its type, description, unit [in
    brackets], valid range and default."""
    lines = ["    Parameters", "    ----------"]
    for f in fields(SlipConfig):
        md = f.metadata
        kind = md["kind"] + (" or None" if md["allow_none"] else "")
        unit = f" [{md['unit']}]" if md["unit"] else ""
        lo = "-inf" if md["lo"] is None else f"{md['lo']:g}"
        hi = "inf" if md["hi"] is None else f"{md['hi']:g}"
        rng = f"{'(' if md['lo_open'] else '['}{lo}, {hi}]"
        text = f"{md['doc']}{unit}; in {rng}, default {f.default!r}"
        lines.append(f"    {f.name} : {kind}")
        lines += ["        " + t for t in textwrap.wrap(text, 84)]
    lines += [
        "",
        "    Raises",
        "    ------",
        "    ValueError",
        "        A value of the wrong type or outside its range, gross_rate_min_hz above",
        "        gross_rate_max_hz, or member_history below texture_min_intervals + 1.",
    ]
    return "\n".join(lines)


SlipConfig.__doc__ = (SlipConfig.__doc__ or "") + "\n" + _field_list_doc() + "\n"
