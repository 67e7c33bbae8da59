# SPDX-License-Identifier: Apache-2.0
"""Helpers for tests that run real rclpy nodes over DDS in the test process."""
import time


def spin_until(executor, predicate, timeout_s=10.0):
    """Spin `executor` until predicate() is true or the timeout passes; return predicate()."""
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return predicate()


def wait_for_subscribers(executor, publisher, count=1, timeout_s=10.0):
    """Wait until DDS discovery matched `count` subscriptions to `publisher`."""
    return spin_until(executor, lambda: publisher.get_subscription_count() >= count, timeout_s)
