# SPDX-License-Identifier: Apache-2.0
"""Field checks shared by the frame bodies, and their common base class.

Wrong Python types raise TypeError; wrong shapes, dtypes and out-of-range values raise
ValueError with the field name and the allowed range. The decoder builds bodies through
the same checks, so whatever ``encode_frame`` refuses, the decoder rejects (and counts).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from ..geometry import N_CHANNELS
from .layout import _F32, MAX_SAMPLES, FrameType


def _int(name: str, value, lo: int, hi: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__} {value!r}")
    v = int(value)
    if not lo <= v <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}], got {v}")
    return v


def _enum(name: str, cls, value):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be a {cls.__name__}, got {type(value).__name__} {value!r}")
    try:
        return cls(int(value))
    except ValueError:
        allowed = ", ".join(f"{m.name}={m.value}" for m in cls)
        raise ValueError(f"{name} must be one of {allowed}; got {int(value)}") from None


def _v_per_count(value) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(
        value, (int, float, np.integer, np.floating)
    ):
        raise TypeError(f"v_per_count must be a real number, got {type(value).__name__} {value!r}")
    v = float(value)
    try:
        (f32,) = _F32.unpack(_F32.pack(v))  # the value the wire carries
    except OverflowError:
        f32 = math.inf
    if not (math.isfinite(f32) and f32 > 0.0):
        raise ValueError(
            f"v_per_count (volts per ADC count, float32) must be finite and > 0, got {v!r}"
        )
    return f32


def _samples(value) -> np.ndarray:
    try:
        a = np.asarray(value)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"samples must be a (4, N) integer array: {exc}") from None
    if a.ndim != 2 or a.shape[0] != N_CHANNELS:
        raise ValueError(
            f"samples must have shape ({N_CHANNELS}, N), channel-major in the"
            f" channel order of ae_tactile.geometry; got shape {a.shape}"
        )
    n = a.shape[1]
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"samples per channel N must be in [1, {MAX_SAMPLES}], got {n}")
    if a.dtype == np.int16 and not a.flags.writeable:
        return a  # e.g. decoded: a read-only view of immutable frame bytes
    if a.dtype.kind not in "iu":
        raise ValueError(
            f"samples must have an integer dtype (int16 ADC counts), got {a.dtype};"
            " convert explicitly (e.g. np.rint(x).astype(np.int16))"
        )
    if a.dtype.itemsize > 2 or (a.dtype.kind == "u" and a.dtype.itemsize == 2):
        lo, hi = int(a.min()), int(a.max())
        if lo < -32768 or hi > 32767:
            raise ValueError(f"samples must fit in int16 [-32768, 32767], got range [{lo}, {hi}]")
    a = a.astype(np.int16)  # always a private copy, so the frozen body stays frozen
    a.flags.writeable = False
    return a


def _arrays_equal(a, b) -> bool:
    return a.shape == b.shape and bool(np.array_equal(a, b))


class _Body:
    """Common base of the frame bodies (payload dataclasses)."""

    frame_type: ClassVar[FrameType]

    def _pack(self) -> bytes:  # pragma: no cover - every subclass overrides
        raise NotImplementedError

    @classmethod
    def _unpack(cls, buf, off: int, length: int):  # pragma: no cover
        raise NotImplementedError
