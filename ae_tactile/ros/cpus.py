# SPDX-License-Identifier: Apache-2.0
"""Checks of the driver's CPU and hand-topic parameters, and pinning the process to CPUs."""

from __future__ import annotations

import os
import re

#: one item of a CPU list: N or N-M, ASCII digits
_CPU_ITEM = re.compile(r"([0-9]{1,6})(?:-([0-9]{1,6}))?")


def _cpus_possible() -> int:
    """Number of CPU ids this kernel knows (/sys/devices/system/cpu/possible, e.g. '0-7';
    offline ones included), else os.cpu_count()."""
    try:
        with open("/sys/devices/system/cpu/possible") as fh:
            return max(int(v) for v in re.split(r"[-,]", fh.read().strip())) + 1
    except (OSError, ValueError):
        return os.cpu_count() or 1


def cpu_list(text: str) -> set[int]:
    """The CPUs of a list written as for ``taskset -c``: '3', '2-3', '0,2-3' (spaces
    ignored); the empty list is empty. Raises ValueError for anything else, and for CPU
    ids this kernel does not know (before expanding a range)."""
    cpus: set[int] = set()
    text = text.replace(" ", "")
    if not text:
        return cpus
    n = _cpus_possible()
    for part in text.split(","):
        m = _CPU_ITEM.fullmatch(part)
        if m is None:
            raise ValueError(f"{part!r} is not a CPU list item such as '3' or '2-3'")
        first = int(m.group(1))
        last = int(m.group(2)) if m.group(2) else first
        if last < first:
            raise ValueError(f"{part!r}: a range runs upwards")
        if last >= n:
            raise ValueError(f"CPU {last} is not on this machine (CPUs 0-{n - 1})")
        cpus.update(range(first, last + 1))
    return cpus


def cpu_list_problem(text) -> str | None:
    """Why ``text`` is no usable CPU list here (None if it is): not a string, not a list,
    or CPUs this machine does not have. (A CPU that is offline or that a cpuset forbids is
    refused by `pin_process`.)"""
    if not isinstance(text, str):
        return "must be a string such as '3' or '2-3'"
    try:
        cpu_list(text)
    except ValueError as exc:
        return str(exc)
    return None


def hand_topic_problem(text) -> str | None:
    """Why ``text`` is no usable topic for the hand's coincidence test (None if it is, or
    empty: off): every fingertip of the hand must name the same topic, so it is absolute
    ('/hand/apex_packets'), made of letters, digits and '_' between the slashes."""
    if not isinstance(text, str):
        return "must be a string such as '/hand/apex_packets'"
    if text == "":
        return None
    parts = text.split("/")
    if parts[0] != "" or len(parts) < 2 or any(
        not p or not (p[0].isalpha() or p[0] == "_") or not all(c.isalnum() or c == "_" for c in p)
        for p in parts[1:]
    ):
        return "must be empty or an absolute topic name such as '/hand/apex_packets'"
    return None


def pin_process(cpus: set[int]) -> int:
    """Run every thread of this process on ``cpus`` (threads and processes it starts later
    inherit it). Linux sets affinity thread by thread, so each one in /proc/self/task is
    set, twice over (a thread started meanwhile inherits its creator's); returns how many
    threads were set the second time. Raises OSError when this process may not run there
    (a cpuset without those CPUs)."""
    os.sched_setaffinity(0, cpus)  # this thread first: what it may not do, none may
    n = 0
    for _ in range(2):
        n = 0
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setaffinity(int(tid), cpus)
                n += 1
            except ProcessLookupError:  # it ended meanwhile
                pass
    return n


