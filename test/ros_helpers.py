# SPDX-License-Identifier: Apache-2.0
"""Helpers for tests that run real rclpy nodes over DDS in the test process, and for
reading what /proc says of the processes they start."""
import os
import time

#: The longest a test waits for what a working system does [s]: a guard against a hang,
#: never a bound on speed (a node's first start after an install compiles its numba
#: kernels for about a minute; a loaded 2-core machine is slow). Waits for something
#: that must *not* happen pass their own short time.
HANG_GUARD_S = 180.0


def spin_until(executor, predicate, timeout_s=HANG_GUARD_S):
    """Spin `executor` until predicate() is true or the timeout passes; return predicate()."""
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return predicate()


def wait_for_subscribers(executor, publisher, count=1, timeout_s=HANG_GUARD_S):
    """Wait until DDS discovery matched `count` subscriptions to `publisher`."""
    return spin_until(executor, lambda: publisher.get_subscription_count() >= count, timeout_s)


def cpus_allowed(pid: int) -> set[str]:
    """Cpus_allowed_list of every thread of a process (a thread that ends meanwhile is
    skipped)."""
    lists = set()
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/status") as fh:
                lists |= {ln.split(":", 1)[1].strip() for ln in fh
                          if ln.startswith("Cpus_allowed_list")}
        except OSError:
            continue
    return lists


def children(pid: int) -> list[int]:
    """Processes whose parent is pid (from /proc)."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            if ppid == pid:
                out.append(int(d))
    return out
