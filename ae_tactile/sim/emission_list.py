# SPDX-License-Identifier: Apache-2.0
"""Ground truth of a stream: the `EmissionList` columns, exact sample <-> nanosecond
conversions, and the emission process over a fixed list (`StaticEmissions`).

An emission process is any object with ``advance(t_ns) -> EmissionList`` (the emissions
before t_ns not returned yet, deterministically) and ``scene_truth() -> dict``; the
renderers pull from it as time advances (`stream.StreamingSource`, `stream.TriggeredSource`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ae_tactile.sim.emission import COMPRESSION, source_strength_pa_m

KINDS = ("touch", "release", "micro_slip", "slip", "texture")
KIND_CODE = {k: i for i, k in enumerate(KINDS)}

_NS = 1_000_000_000  # [ns/s]


@dataclass(frozen=True)
class EmissionList:
    """Ground truth of emissions, columnar and sorted by (time_ns, event_id).

    time_ns        (N,) int64 emission instant
    point_m        (N, 3) contact point on the sensing surface
    kind           (N,) int8 code into KINDS
    strength_pa_m  (N,) signed source strength S = polarity rho v0^2 / a_c; the jump at
                   distance l is S / l (the "amplitude" of the ground truth)
    speed_m_s, curvature_1_m, alpha_1_s   (N,) Eq. 10 event parameters
    event_id       (N,) int64, unique per emission within a scene
    """

    time_ns: np.ndarray
    point_m: np.ndarray
    kind: np.ndarray
    strength_pa_m: np.ndarray
    speed_m_s: np.ndarray
    curvature_1_m: np.ndarray
    alpha_1_s: np.ndarray
    event_id: np.ndarray

    def __len__(self):
        return int(self.time_ns.shape[0])

    @property
    def polarity(self) -> np.ndarray:
        """(N,) +1 compression, -1 rarefaction (the sign of the source strength)."""
        return np.sign(self.strength_pa_m)

    @property
    def kind_names(self) -> list[str]:
        return [KINDS[k] for k in self.kind]

    @classmethod
    def empty(cls) -> "EmissionList":
        z = np.zeros(0)
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int8), z, z, z, z,
                   np.zeros(0, np.int64))

    @classmethod
    def create(cls, time_ns, point_m, kind, *, polarity=COMPRESSION, speed_m_s, curvature_1_m,
               alpha_1_s, density_kg_m3, event_id) -> "EmissionList":
        """Build a list sorted by (time_ns, event_id); scalars broadcast to every emission.

        Parameters
        ----------
        time_ns : array_like
            Emission instants (N,) [ns].
        point_m : array_like
            Contact points (N, 3) on the sensing surface [m].
        kind : str or array_like
            A name of `KINDS`, or names / codes per emission.
        polarity : int or array_like
            `emission.COMPRESSION` (+1) or `emission.RAREFACTION` (-1).
        speed_m_s, curvature_1_m, alpha_1_s : float or array_like
            Eq. 10 event parameters [m/s], [1/m], [1/s].
        density_kg_m3 : float
            Density of the medium [kg/m^3] (sets the source strength).
        event_id : int or array_like
            Unique id per emission within a scene.

        Returns
        -------
        EmissionList
        """
        t = np.atleast_1d(np.asarray(time_ns, dtype=np.int64))
        n = t.shape[0]
        p = np.asarray(point_m, dtype=float).reshape(n, 3)
        if isinstance(kind, str):
            k = np.full(n, KIND_CODE[kind], np.int8)
        else:
            k = np.asarray([KIND_CODE[x] if isinstance(x, str) else int(x)
                            for x in np.atleast_1d(kind)],
                           np.int8)
            k = np.broadcast_to(k, (n,)).copy()
        b = lambda v: np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy()   # noqa: E731
        pol, v, a, al = b(polarity), b(speed_m_s), b(curvature_1_m), b(alpha_1_s)
        s = source_strength_pa_m(v, a, density_kg_m3, pol)
        eid = np.broadcast_to(np.asarray(event_id, dtype=np.int64), (n,)).copy()
        out = cls(t, p, k, s, v, a, al, eid)
        return out.sorted()

    def sorted(self) -> "EmissionList":
        order = np.lexsort((self.event_id, self.time_ns))
        return self.take(order)

    def take(self, idx) -> "EmissionList":
        return EmissionList(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))

    @staticmethod
    def concat(lists) -> "EmissionList":
        lists = [x for x in lists if len(x)]
        if not lists:
            return EmissionList.empty()
        f = EmissionList.__dataclass_fields__
        return EmissionList(*(np.concatenate([getattr(x, k) for x in lists]) for k in f)).sorted()

    def between(self, t0_ns, t1_ns) -> "EmissionList":
        """Emissions with t0 <= time_ns < t1."""
        i0, i1 = np.searchsorted(self.time_ns, [t0_ns, t1_ns], side="left")
        return self.take(slice(int(i0), int(i1)))

    def to_records(self) -> list[dict]:
        """Plain-Python ground-truth records (for YAML/JSON/printing)."""
        return [dict(event_id=int(self.event_id[i]), time_ns=int(self.time_ns[i]),
                     type=KINDS[self.kind[i]], point_m=[float(x) for x in self.point_m[i]],
                     strength_pa_m=float(self.strength_pa_m[i]),
                     speed_m_s=float(self.speed_m_s[i]),
                     curvature_1_m=float(self.curvature_1_m[i]),
                     alpha_1_s=float(self.alpha_1_s[i]))
                for i in range(len(self))]

    def as_arrays(self, prefix="truth_") -> dict:
        """Arrays for ``np.savez`` (kind as codes plus the KINDS table)."""
        d = {prefix + k: getattr(self, k) for k in self.__dataclass_fields__}
        d[prefix + "kind_names"] = np.array(KINDS)
        return d


def sample_index_of_ns(time_ns, sample_rate_hz) -> tuple[np.ndarray, np.ndarray]:
    """(n, frac_s): sample n = floor(t fs) in exact integer arithmetic, and t - n/fs (s)."""
    t = np.asarray(time_ns, dtype=np.int64)
    fs = np.int64(int(round(sample_rate_hz)))
    sec, rem = np.divmod(t, np.int64(_NS))
    prod = rem * fs                              # < 1e9 * fs, fits int64 for fs < 9e9
    n = sec * fs + prod // np.int64(_NS)
    frac = (prod % np.int64(_NS)).astype(float) / (float(_NS) * float(fs))
    return n, frac


def time_ns_of_sample(n, sample_rate_hz) -> np.ndarray:
    """Start time (ns, rounded down) of absolute sample n."""
    n = np.asarray(n, dtype=np.int64)
    fs = np.int64(int(round(sample_rate_hz)))
    sec, rem = np.divmod(n, fs)
    return sec * np.int64(_NS) + (rem * np.int64(_NS)) // fs


class StaticEmissions:
    """An emission process over a fixed, pre-generated `EmissionList`."""

    def __init__(self, emissions: EmissionList, truth: dict | None = None):
        self.emissions = emissions.sorted()
        self.truth = dict(truth or {})
        self._horizon_ns = None

    def advance(self, t_ns: int) -> EmissionList:
        """Emissions with previous horizon <= time_ns < t_ns (everything before, first call)."""
        lo = np.iinfo(np.int64).min if self._horizon_ns is None else self._horizon_ns
        if self._horizon_ns is not None and t_ns <= self._horizon_ns:
            return EmissionList.empty()
        self._horizon_ns = int(t_ns)
        return self.emissions.between(lo, t_ns)

    def scene_truth(self) -> dict:
        return dict(self.truth)


def as_process(src):
    """``src`` as an emission process: an `EmissionList` is wrapped in `StaticEmissions`;
    an object with ``advance`` is returned as it is."""
    if isinstance(src, EmissionList):
        return StaticEmissions(src)
    if hasattr(src, "advance"):
        return src
    raise TypeError("expected an EmissionList or an emission process with advance(t_ns)")
