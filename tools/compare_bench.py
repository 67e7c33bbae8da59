#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""Compare the figures of two benchmark runs: a refactor must leave them unchanged.

    python3 tools/compare_bench.py A_DIR B_DIR [--rtol 1e-9] [--atol 0] [--max-lines 200]

Walks every ``*.json`` under A_DIR and B_DIR (matched by their path relative to the
directory; e.g. the per-bench folders the reduced runs of bench/bench_*.py write) and
compares every leaf: numbers within ``--rtol`` (relative to the larger magnitude) or
``--atol``, NaN equal to NaN, booleans, None and text exactly; lists element by element.
A leaf is skipped as timing when a key on its path names wall-clock or CPU time, a rate
per wall second, a latency, the machine's load or heap use (``TIMING``), and as
environment when it names the machine or software versions (``ENVIRONMENT``); durations
in simulated time (``slip_delay_ms``, ``lead_ms``, ``time_to_gross_slip_s``, ...) are
figures. Keys or files present in one run only are listed. Exit status 1 when a figure
differs or is in one run only, else 0.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

#: keys naming a measured time, rate per wall second, latency, load or memory use
TIMING = re.compile(
    r"^(timing|timing_s|detector_speed|interference_speed|one_window_ms)$|^(replayed|floor)_"
    r"|(^|_)(cpu|wall|seconds|elapsed|latency|throughput|heap|realtime|real_time|run_time)(_|$)"
    r"|^(load|loadavg)(_|$)|^(total_s|calibration_s|seconds_per_rate)$|_per_s$"
    r"|^(us|ms)_|_(us|ms)_per_|_ms_p\d+$|^(median|mean|max|min|p\d+)_(us|ms)$"
    r"|_quarter_median_ms$|^stamp_to_\w+_ms$|(after|again|delivered|packet)(_unplug)?_s$"
)
#: figures though TIMING matches them or a key above them: per second of simulated time, a
#: trial parameter, the compiled and numpy paths' agreement (in the overlap bench's timing)
FIGURES = {
    "emissions_per_s", "scene_emissions_per_s", "tangential_load_rate_n_per_s", "same_points"
}
#: the machine and software versions
ENVIRONMENT = {
    "python", "numpy", "numba", "machine", "processor", "platform", "environment", "cpu_count",
    "cpus", "cores_used", "harness_cpus", "driver_cpu", "timestamp",
}


def skip_kind(path: tuple) -> str | None:
    """'timing', 'environment' or None (a figure) for a leaf's path of keys."""
    keys = [k for k in path if isinstance(k, str)]
    if any(k in ENVIRONMENT for k in keys):
        return "environment"
    if keys and keys[-1] in FIGURES:
        return None
    if any(k not in FIGURES and TIMING.search(k) for k in keys):
        return "timing"
    return None


def leaves(obj, path=()):
    """(path, value) of every leaf; an empty list or dict is a leaf."""
    if isinstance(obj, dict) and obj:
        for k, v in obj.items():
            yield from leaves(v, (*path, str(k)))
    elif isinstance(obj, list) and obj:
        for i, v in enumerate(obj):
            yield from leaves(v, (*path, i))
    else:
        yield path, obj


def is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def same(a, b, rtol: float, atol: float) -> bool:
    """Numbers within the tolerances (NaN equals NaN); anything else exactly, type included."""
    if not (is_num(a) and is_num(b)):
        return type(a) is type(b) and a == b
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return a == b or abs(a - b) <= max(atol, rtol * max(abs(a), abs(b)))


def show(path: tuple) -> str:
    return "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in path)[1:]


def diff_line(rel: str, path: tuple, va, vb) -> str:
    """One differing figure: file, key path, both values and their relative difference."""
    rel_d = ""
    if is_num(va) and is_num(vb):
        rel_d = f"  (rel {abs(va - vb) / max(abs(va), abs(vb), 1e-300):.2g})"
    return f"{rel}:{show(path)}  A={va!r}  B={vb!r}{rel_d}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("a_dir", type=Path)
    ap.add_argument("b_dir", type=Path)
    ap.add_argument("--rtol", type=float, default=1e-9, help="relative tolerance (default 1e-9)")
    ap.add_argument("--atol", type=float, default=0.0, help="absolute tolerance (default 0)")
    ap.add_argument("--max-lines", type=int, default=200, help="differences printed at most")
    args = ap.parse_args(argv)
    files = {}
    for side, root in (("A", args.a_dir), ("B", args.b_dir)):
        for f in sorted(root.rglob("*.json")):
            files.setdefault(str(f.relative_to(root)), {})[side] = f
    n_fig = n_skip = n_env = 0
    differ, only = [], []
    for rel, sides in sorted(files.items()):
        if len(sides) < 2:
            only.append(f"{rel} (file only in {', '.join(sides)})")
            continue
        a, b = ({p: v for p, v in leaves(json.loads(sides[s].read_text()))} for s in "AB")
        for path in sorted(a.keys() | b.keys(), key=lambda p: [str(k).zfill(9) for k in p]):
            kind = skip_kind(path)
            if kind == "environment":
                n_env += 1
            elif kind == "timing":
                n_skip += 1
            elif path not in a or path not in b:
                only.append(f"{rel}:{show(path)} (only in {'A' if path in a else 'B'})")
            else:
                n_fig += 1
                if not same(a[path], b[path], args.rtol, args.atol):
                    differ.append(diff_line(rel, path, a[path], b[path]))
    for title, rows in (("figures that differ", differ), ("in one run only", only)):
        if rows:
            print(f"{title} ({len(rows)}):")
            for row in rows[: args.max_lines]:
                print("  " + row)
            if len(rows) > args.max_lines:
                print(f"  ... and {len(rows) - args.max_lines} more")
    print(
        f"{n_fig} figures compared, {len(differ)} differ, {n_skip} timing values skipped"
        f" ({n_env} environment values skipped, {len(only)} in one run only; rtol {args.rtol:g})"
    )
    return 1 if differ or only else 0


if __name__ == "__main__":
    sys.exit(main())
