# SPDX-License-Identifier: Apache-2.0
"""A picture of what happened in a run: one PNG with three panels.

- Top view of the fingertip (x, y in mm): the sphere's outline (radius R), the 2x2 PVDF
  matrix at (+-a, +-a), every event by type (hollow markers: lower hemisphere, z < 0, seen
  through the body), every localized emission as a small dot and the ground truth where
  known.
- Timeline: events by type against time, the reported contact state as coloured spans
  and, where the scene's truth is known, the true state under it.
- Latency histogram (ms) with median and 95th percentile.

Plain data in, no rclpy: the live monitor and the bag replay tool both call
`write_run_summary`. Events are a list of dicts or a dict of equal-length arrays with
keys ``time_s``, ``type`` (name such as "TOUCH" or the ContactEvent number), ``x_m``,
``y_m``, ``z_m`` and optionally ``latency_s``. Rows with a non-finite time or position
are left out of the panel that needs them and counted in the returned summary.
matplotlib is optional at run time: without it `ReportUnavailable` says how to get it.
"""
from __future__ import annotations

import math
import os
from typing import Any, Iterable, Mapping

import numpy as np

from .records import ContactState, EventType

#: Event type names in ContactEvent order (1..5), with their plot style.
EVENT_TYPES = tuple(t.name for t in EventType)  # index + 1 = the type's value
STYLE = {
    "TOUCH": ("#1f77b4", "o"),
    "DETOUCH": ("#ff7f0e", "s"),
    "SLIP_PRECURSOR": ("#2ca02c", "^"),
    "SLIP": ("#d62728", "D"),
    "TEXTURE": ("#9467bd", "P"),
}
STATE_COLOURS = {ContactState.NO_CONTACT.name: "#dddddd", ContactState.STICK.name: "#9ecae1",
                 ContactState.INCIPIENT_SLIP.name: "#fdd0a2",
                 ContactState.GROSS_SLIP.name: "#fc9272"}
TRUTH_COLOUR = "#000000"


class ReportUnavailable(RuntimeError):
    """matplotlib is not installed: no PNG summary (everything else works)."""


def _columns(rows, keys: Iterable[str], required: Iterable[str], what: str) -> dict:
    """Equal-length numpy columns from a list of dicts, a dict of arrays or a structured
    array; missing optional keys become NaN. ValueError names what is wrong."""
    keys, required = list(keys), set(required)
    if rows is None:
        rows = []
    if isinstance(rows, np.ndarray) and rows.dtype.names:
        rows = {k: rows[k] for k in rows.dtype.names}
    if isinstance(rows, Mapping):
        n = None
        cols = {}
        for k in keys:
            if k not in rows:
                if k in required:
                    raise ValueError(f"{what}: missing column {k!r}")
                continue
            col = np.asarray(rows[k])
            if col.ndim != 1:
                raise ValueError(f"{what}: column {k!r} must be 1-D, got shape {col.shape}")
            if n is not None and len(col) != n:
                raise ValueError(f"{what}: column {k!r} has {len(col)} rows, expected {n}")
            n = len(col)
            cols[k] = col
        n = n or 0
    else:
        rows = list(rows)
        for i, r in enumerate(rows):
            if not isinstance(r, Mapping):
                raise ValueError(f"{what}: row {i} is a {type(r).__name__}, expected a dict")
            missing = required - set(r)
            if missing:
                raise ValueError(f"{what}: row {i} misses {sorted(missing)}")
        n = len(rows)
        cols = {k: np.array([r.get(k) for r in rows], dtype=object) for k in keys
                if any(k in r for r in rows)}
    out = {}
    for k in keys:
        if k == "type" or k == "state":
            out[k] = cols.get(k, np.full(n, None, dtype=object))
            continue
        col = cols.get(k)
        if col is None:
            out[k] = np.full(n, np.nan)
            continue
        try:
            out[k] = np.array([np.nan if v is None else v for v in col], dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{what}: column {k!r} is not numeric ({exc})") from exc
    out["n"] = n
    return out


def _type_name(value) -> str:
    if isinstance(value, (int, np.integer)) and 1 <= int(value) <= len(EVENT_TYPES):
        return EVENT_TYPES[int(value) - 1]
    name = str(value).upper()
    if name not in EVENT_TYPES:
        raise ValueError(f"event type {value!r} is not one of {', '.join(EVENT_TYPES)} (or 1..5)")
    return name


def _state_spans(states, end_time_s: float) -> list[tuple[str, float, float]]:
    """(state name, start, duration) spans from time-ordered state changes."""
    cols = _columns(states, ("time_s", "state"), ("time_s", "state"), "contact_state")
    t = cols["time_s"]
    ok = np.isfinite(t)
    order = np.argsort(t[ok], kind="stable")
    times, names = t[ok][order], [str(s).upper() for s in cols["state"][ok][order]]
    spans = []
    for i, (t0, name) in enumerate(zip(times, names)):
        t1 = times[i + 1] if i + 1 < len(times) else max(end_time_s, t0)
        if t1 > t0:
            spans.append((name, float(t0), float(t1 - t0)))
    return spans


def write_run_summary(path: str | os.PathLike, events=None, *, truth=None, contact_state=None,
                      truth_state=None, emissions=None, latencies_s=None,
                      radius_m: float = 10e-3,
                      element_offset_m: float = 1.5e-3, title: str = "",
                      size_px: tuple[int, int] = (1500, 900), dpi: int = 100) -> dict[str, Any]:
    """Write the PNG summary of a run.

    Parameters
    ----------
    path : str or os.PathLike
        The PNG file.
    events : list of dict, dict of arrays or structured array, optional
        Rows with time_s, type, x_m, y_m, z_m [, latency_s] (see the module docstring).
    truth : same forms, optional
        Rows with x_m, y_m [, z_m, time_s]: ground-truth contact points [m].
    contact_state : same forms, optional
        Rows with time_s, state (e.g. NO_CONTACT, STICK, GROSS_SLIP): state changes.
    truth_state : same forms, optional
        The true state's changes (the scene's truth, `ae_tactile.scoring`), drawn under
        the reported state.
    emissions : same forms, optional
        Rows with x_m, y_m [, time_s]: every localized emission [m] (small dots).
    latencies_s : array_like, optional
        Latencies [s]; default: the events' latency_s column.
    radius_m : float
        Sphere radius R [m].
    element_offset_m : float
        PVDF centres at (+-a, +-a) [m].
    title : str
        Figure title.
    size_px : tuple of int
        Width and height [pixel], each 200..10000.
    dpi : int
        Resolution [dot/inch].

    Returns
    -------
    dict
        What was plotted: "path", "events", "events_plotted", "events_without_position",
        "events_without_time", "truth_points", "emissions_plotted", "latencies",
        "latency_median_s", "latency_p95_s".

    Raises
    ------
    ReportUnavailable
        matplotlib is not installed.
    ValueError
        A bad argument or column (the message names it).
    """
    width_px, height_px = _check_sizes(radius_m, element_offset_m, size_px, dpi)
    fig, ax_top, ax_time, ax_lat = _figure(width_px, height_px, dpi, title)

    ev = _columns(events, ("time_s", "type", "x_m", "y_m", "z_m", "latency_s"),
                  ("time_s", "type"), "events")
    types = np.array([_type_name(v) for v in ev["type"]], dtype=object)
    tr = _columns(truth, ("x_m", "y_m", "z_m", "time_s"), ("x_m", "y_m"), "truth")
    if latencies_s is None:
        lat = ev["latency_s"]
    else:
        lat = np.asarray(latencies_s, dtype=float)
        if lat.ndim != 1:
            raise ValueError(f"latencies_s must be 1-D, got shape {lat.shape}")
    lat = lat[np.isfinite(lat)]

    has_xy = np.isfinite(ev["x_m"]) & np.isfinite(ev["y_m"])
    has_t = np.isfinite(ev["time_s"])
    n_em = _emission_dots(ax_top, emissions)
    tr_xy = _top_view(ax_top, ev, types, has_xy, tr, radius_m, element_offset_m)
    _timeline(ax_time, ev, types, has_t, contact_state, truth_state)
    summary_lat = _latency_histogram(ax_lat, lat)

    path = os.fspath(path)
    fig.savefig(path, dpi=dpi, format="png")
    return {"path": path, "events": ev["n"], "events_plotted": int(has_xy.sum()),
            "events_without_position": int((~has_xy).sum()),
            "events_without_time": int((~has_t).sum()), "truth_points": int(tr_xy.sum()),
            "emissions_plotted": n_em, "latencies": int(lat.size), **summary_lat}


def _check_sizes(radius_m, element_offset_m, size_px, dpi) -> tuple[int, int]:
    """(width, height) [pixel]; ValueError naming a bad size."""
    if not (math.isfinite(radius_m) and radius_m > 0):
        raise ValueError(f"radius_m must be a positive number, got {radius_m!r}")
    if not (math.isfinite(element_offset_m) and 0 < element_offset_m < radius_m):
        raise ValueError(f"element_offset_m must be in (0, radius_m), got {element_offset_m!r}")
    width_px, height_px = (int(v) for v in size_px)
    if not (200 <= width_px <= 10000 and 200 <= height_px <= 10000) or dpi <= 0:
        raise ValueError(f"size_px must be within 200..10000 pixels, got {size_px!r}")
    return width_px, height_px


def _emission_dots(ax, emissions) -> int:
    """Every localized emission as a small grey dot on the top view [mm]; returns how many
    had a position."""
    em = _columns(emissions, ("x_m", "y_m", "time_s"), ("x_m", "y_m"), "emissions")
    if not em["n"]:
        return 0
    x, y = em["x_m"].astype(float), em["y_m"].astype(float)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.any():
        ax.scatter(x[ok] * 1e3, y[ok] * 1e3, s=4, color="#888888", zorder=2,
                   label=f"emissions ({int(ok.sum())})")
    return int(ok.sum())


def _figure(width_px: int, height_px: int, dpi: int, title: str):
    """The figure and its three panels (top view, timeline, latency)."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # lazy: optional, slow
        from matplotlib.figure import Figure  # lazy: optional (ReportUnavailable), slow
    except ImportError as exc:
        raise ReportUnavailable(
            "PNG summaries need matplotlib, which is not installed (pip install matplotlib, "
            f"or apt install python3-matplotlib): {exc}") from exc
    fig = Figure(figsize=(width_px / dpi, height_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 2, width_ratios=(1.0, 1.35), hspace=0.35, wspace=0.32,
                            left=0.06, right=0.98, top=0.9, bottom=0.1)
    ax_top = fig.add_subplot(grid[:, 0])
    ax_time = fig.add_subplot(grid[0, 1])
    ax_lat = fig.add_subplot(grid[1, 1])
    if title:
        fig.suptitle(title)
    return fig, ax_top, ax_time, ax_lat


def _top_view(ax, ev: dict, types, has_xy, tr: dict, radius_m: float,
              element_offset_m: float):
    """The fingertip from above (mm): outline, PVDF elements, truth, events by type
    (hollow: lower hemisphere). Returns which truth rows have a position."""
    # lazy: matplotlib is optional; write_run_summary checked it is there
    from matplotlib.patches import Circle, Rectangle

    scale = 1e3   # m -> mm
    r_mm, a_mm = radius_m * scale, element_offset_m * scale
    ax.add_patch(Circle((0, 0), r_mm, fill=False, lw=1.5, color="#555555"))
    side = 0.8 * a_mm
    for sx in (-1, 1):
        for sy in (-1, 1):
            ax.add_patch(Rectangle((sx * a_mm - side / 2, sy * a_mm - side / 2), side, side,
                                   color="#bbbbbb", zorder=1))
    tr_xy = np.isfinite(tr["x_m"]) & np.isfinite(tr["y_m"])
    if tr_xy.any():
        ax.scatter(tr["x_m"][tr_xy] * scale, tr["y_m"][tr_xy] * scale, marker="x", s=70,
                   color=TRUTH_COLOUR, lw=1.5, zorder=4, label="ground truth")
    for name in EVENT_TYPES:
        colour, marker = STYLE[name]
        sel = has_xy & (types == name)
        if not sel.any():
            continue
        below = sel & (ev["z_m"] < 0)
        above = sel & ~below
        if above.any():
            ax.scatter(ev["x_m"][above] * scale, ev["y_m"][above] * scale, marker=marker,
                       s=36, color=colour, zorder=3, label=f"{name} ({int(sel.sum())})")
        if below.any():
            ax.scatter(ev["x_m"][below] * scale, ev["y_m"][below] * scale, marker=marker,
                       s=36, facecolors="none", edgecolors=colour, zorder=3,
                       label=None if above.any() else f"{name} ({int(sel.sum())})")
    lim = 1.1 * r_mm
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"fingertip from above: R = {r_mm:g} mm, PVDF at (±{a_mm:g}, ±{a_mm:g}) mm")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3,
                  fontsize="small", frameon=False)
    return tr_xy


def _timeline(ax, ev: dict, types, has_t, contact_state, truth_state=None) -> None:
    """Events by type against time [s], the reported contact state as coloured spans and
    the true state's under them (row -1) when given."""
    t_end = float(np.max(ev["time_s"][has_t])) if has_t.any() else 0.0
    spans = _state_spans(contact_state, t_end) if contact_state is not None else []
    truth_spans = _state_spans(truth_state, t_end) if truth_state is not None else []
    if spans or truth_spans:
        t_end = max([t_end] + [s0 + d for _, s0, d in spans + truth_spans])
    t0_plot = min([0.0] + [s0 for _, s0, _ in spans + truth_spans])
    for row, rows in ((0, spans), (-1, truth_spans)):
        for name, start, duration in rows:
            ax.broken_barh([(start, duration)], (row - 0.4, 0.8),
                           facecolors=STATE_COLOURS.get(name, "#eeeeee"))
            if duration >= 0.12 * max(t_end - t0_plot, 1e-9):  # narrow spans: colour only
                ax.text(start, row, f" {name}", va="center", fontsize="x-small", clip_on=True)
    for row, name in enumerate(EVENT_TYPES, start=1):
        colour, marker = STYLE[name]
        sel = has_t & (types == name)
        if sel.any():
            ax.scatter(ev["time_s"][sel], np.full(int(sel.sum()), row), marker=marker,
                       s=28, color=colour)
    low = -1 if truth_spans else 0
    labels = (["true state"] if truth_spans else []) + ["contact state", *EVENT_TYPES]
    ax.set_yticks(range(low, len(EVENT_TYPES) + 1), labels, fontsize="small")
    ax.set_ylim(low - 0.7, len(EVENT_TYPES) + 0.7)
    ax.set_xlabel("time (s)")
    ax.set_title(f"timeline: {int(has_t.sum())} events")
    if not has_t.any() and not spans:
        ax.set_xlim(0.0, 1.0)


def _latency_histogram(ax, lat) -> dict:
    """Latency histogram [ms] with median and 95th percentile; returns them [s]."""
    summary_lat = {"latency_median_s": math.nan, "latency_p95_s": math.nan}
    if lat.size:
        lat_ms = lat * 1e3
        ax.hist(lat_ms, bins=min(50, max(5, int(math.sqrt(lat.size)) * 2)), color="#4c72b0")
        med, p95 = np.percentile(lat_ms, [50, 95])
        summary_lat = {"latency_median_s": float(med) / 1e3, "latency_p95_s": float(p95) / 1e3}
        for value, style in ((med, "-"), (p95, "--")):
            ax.axvline(value, color="#333333", ls=style, lw=1)
        ax.set_title(f"latency: median {med:.2f} ms, 95% {p95:.2f} ms ({lat.size} events)")
    else:
        ax.text(0.5, 0.5, "no latency data", ha="center", va="center",
                transform=ax.transAxes)
        ax.set_title("latency")
    ax.set_xlabel("latency (ms)")
    ax.set_ylabel("events")
    return summary_lat
