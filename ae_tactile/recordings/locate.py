# SPDX-License-Identifier: Apache-2.0
"""Planar location of AE events from arrival-time differences (any sensor layout).

Hits of different channels within the coincidence window (the longest sensor distance over
the wave speed) form one event; its first hit opens it. With n >= 3 sensors hit, the
source (x, y) minimises, as Vallen's LUCY location does,

    r_i(x, y) = (|p - s_i| - |p - s_0|) - v (t_i - t_0),   i = 1 .. n - 1,
    LUCY = ||r|| / sqrt(n - 1)   [m],

s_0, t_0 being the first-hit sensor and its arrival time: a coarse grid over the sensors'
bounding box (half its size added on every side) gives the start, a least-squares fit
finishes it. LUCY is the location's quality: the distance misfit that one sensor carries
on average (0 for consistent times).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
from scipy.optimize import least_squares

#: grid points per axis of the starting search
GRID_POINTS = 41


@dataclass
class PlanarEvent:
    """One located event: the source (x, y) [m] and its LUCY [m], or why it has none."""

    time_s: float  # first arrival [s]
    channels: tuple
    arrival_times_s: tuple
    hit_indices: tuple
    x_m: float = math.nan
    y_m: float = math.nan
    lucy_m: float = math.nan
    reason: str = ""  # '' located; else why not (e.g. 'fewer than 3 sensors')


def parse_sensor_xy(text: str) -> np.ndarray:
    """Sensor positions from ``"x1,y1;x2,y2;..."`` [m] -> (n, 2).

    Parameters
    ----------
    text : str

    Returns
    -------
    numpy.ndarray
    """
    try:
        xy = np.array([[float(v) for v in pair.split(",")] for pair in text.split(";")
                       if pair.strip()], dtype=float)
    except ValueError:
        raise ValueError(f"sensor positions must read 'x1,y1;x2,y2;...' in m, got "
                         f"{text!r}") from None
    if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] < 3 or not np.isfinite(xy).all():
        raise ValueError(f"need at least 3 finite 'x,y' sensor positions, got {text!r}")
    return xy


def read_vallen_setup(path) -> tuple[dict, float]:
    """Sensor positions and wave speed of a Vallen setup file (.vaex), as vallenae's
    location example reads them: ``ChannelPos`` (Chan, X, Y) and ``Location`` Velocity
    [km/s] (positions taken as metres).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    positions : dict
        channel number -> (x, y) [m].
    velocity_m_s : float
    """
    try:
        root = ElementTree.parse(str(path)).getroot()
    except (ElementTree.ParseError, OSError) as exc:
        raise ValueError(f"{path}: not a readable Vallen setup file ({exc})") from None
    pos = {int(e.get("Chan")): (float(e.get("X")), float(e.get("Y")))
           for e in root.iter("ChannelPos")}
    loc = next((e for e in root.iter("Location") if e.get("Velocity")), None)
    if not pos or loc is None:
        raise ValueError(f"{path}: no ChannelPos / Location Velocity in the setup")
    return pos, float(loc.get("Velocity")) * 1e3


def lucy_m(point_xy, arrival_times_s, sensor_xy_m, velocity_m_s: float) -> float:
    """LUCY [m] of a source at ``point_xy`` for arrival times at the sensors (first
    entry: the reference sensor)."""
    r = _residuals(np.asarray(point_xy, float), np.asarray(arrival_times_s, float),
                   np.asarray(sensor_xy_m, float), float(velocity_m_s))
    return float(np.linalg.norm(r) / math.sqrt(len(r)))


def _residuals(p, t, s, v):
    d = np.hypot(p[0] - s[:, 0], p[1] - s[:, 1])
    return (d[1:] - d[0]) - v * (t[1:] - t[0])


def locate_planar(arrival_times_s, sensor_xy_m, velocity_m_s: float) -> tuple[float, float,
                                                                                float]:
    """Least-LUCY source of one event.

    Parameters
    ----------
    arrival_times_s : array_like
        (n,) [s], n >= 3, one per sensor (any order; the earliest is the reference).
    sensor_xy_m : array_like
        (n, 2) [m], in the same order.
    velocity_m_s : float
        Wave speed [m/s].

    Returns
    -------
    x_m, y_m, lucy_m : float
    """
    t = np.asarray(arrival_times_s, float)
    s = np.asarray(sensor_xy_m, float).reshape(-1, 2)
    v = float(velocity_m_s)
    if t.shape != (s.shape[0],) or t.size < 3:
        raise ValueError(f"need >= 3 arrival times with one sensor each, got {t.shape} and "
                         f"{s.shape}")
    if not (np.isfinite(t).all() and np.isfinite(s).all() and math.isfinite(v) and v > 0):
        raise ValueError("arrival times, positions and a velocity > 0 must be finite")
    order = np.argsort(t, kind="stable")
    t, s = t[order], s[order]
    lo, hi = s.min(axis=0), s.max(axis=0)
    span = np.maximum(hi - lo, 1e-6)
    gx = np.linspace(lo[0] - span[0] / 2, hi[0] + span[0] / 2, GRID_POINTS)
    gy = np.linspace(lo[1] - span[1] / 2, hi[1] + span[1] / 2, GRID_POINTS)
    px, py = np.meshgrid(gx, gy)
    d = np.hypot(px[..., None] - s[:, 0], py[..., None] - s[:, 1])
    r = (d[..., 1:] - d[..., :1]) - v * (t[1:] - t[0])
    k = np.unravel_index(np.argmin((r * r).sum(axis=-1)), px.shape)
    fit = least_squares(_residuals, [px[k], py[k]], args=(t, s, v), method="lm",
                        xtol=1e-12, ftol=1e-12)
    x, y = (float(c) for c in fit.x)
    return x, y, lucy_m((x, y), t, s, v)


def group_hits(hits, window_s: float) -> list[list[int]]:
    """Events: the first hit not yet taken opens one, the first hit of every other
    channel within ``window_s`` of it joins (indices into ``hits``, time order)."""
    order = sorted(range(len(hits)), key=lambda i: hits[i].onset_time_s)
    taken, events = set(), []
    for n, i in enumerate(order):
        if i in taken:
            continue
        ev, chans = [i], {hits[i].channel}
        for j in order[n + 1:]:
            if hits[j].onset_time_s - hits[i].onset_time_s > window_s:
                break
            if j not in taken and hits[j].channel not in chans:
                ev.append(j)
                chans.add(hits[j].channel)
        taken.update(ev)
        events.append(ev)
    return events


def sensor_map(channels, sensor_xy) -> dict:
    """channel -> (x, y) [m]: a dict as given, or an (n, 2) array in the order of the
    sorted channel ids (Vallen 1, 2, ...; a WAV's 0, 1, ...)."""
    if isinstance(sensor_xy, dict):
        return {k: tuple(map(float, v)) for k, v in sensor_xy.items()}
    xy = np.asarray(sensor_xy, float).reshape(-1, 2)
    ids = sorted(set(channels), key=lambda c: (str(type(c)), c))
    if len(ids) > xy.shape[0]:
        raise ValueError(f"{len(ids)} channels ({', '.join(map(str, ids))}) but only "
                         f"{xy.shape[0]} sensor positions")
    return {c: (float(xy[i, 0]), float(xy[i, 1])) for i, c in enumerate(ids)}


def locate_events(hits, sensor_xy, velocity_m_s: float,
                  window_s: float | None = None) -> list[PlanarEvent]:
    """Group hits into events and locate each from the hits' onsets.

    Parameters
    ----------
    hits : list of Hit
    sensor_xy : dict or array_like
        channel -> (x, y) [m], or (n, 2) in sorted channel order (`sensor_map`).
    velocity_m_s : float
        Wave speed [m/s].
    window_s : float or None
        Coincidence window [s]; None: the longest sensor distance over the speed, plus 10 %.

    Returns
    -------
    list of PlanarEvent
    """
    v = float(velocity_m_s)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"velocity_m_s must be finite and > 0, got {velocity_m_s!r}")
    pos = sensor_map([h.channel for h in hits], sensor_xy)
    xy = np.array(list(pos.values()), float)
    if window_s is None:
        far = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1)).max()
        window_s = 1.1 * far / v
    out = []
    idx = [i for i, h in enumerate(hits) if h.channel in pos]
    sel = [hits[i] for i in idx]
    for ev in group_hits(sel, window_s):
        hs = [sel[i] for i in ev]
        e = PlanarEvent(hs[0].onset_time_s, tuple(h.channel for h in hs),
                        tuple(h.onset_time_s for h in hs), tuple(idx[i] for i in ev))
        if len(hs) < 3:
            e.reason = f"{len(hs)} sensor(s) hit, location needs 3"
        else:
            e.x_m, e.y_m, e.lucy_m = locate_planar(e.arrival_times_s,
                                                   [pos[c] for c in e.channels], v)
        out.append(e)
    return out


def setup_beside(path) -> Path | None:
    """The Vallen setup file (.vaex) beside a pridb/tradb, if there is one."""
    p = Path(path)
    if p.suffix.lower() not in (".pridb", ".tradb"):
        return None
    vaex = p.with_suffix(".vaex")
    return vaex if vaex.is_file() else None
