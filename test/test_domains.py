# SPDX-License-Identifier: Apache-2.0
"""Two test runs on one machine never share a ROS domain: `conftest.claim_domain` skips an
id whose lock another process holds, and a lock held by a process that ended is free."""
import os
import subprocess
import sys

from conftest import DOMAIN_LOCK_DIR, claim_domain

_HOLDER = """
import fcntl, os, sys
fh = open(os.path.join(sys.argv[1], sys.argv[2] + ".lock"), "a")
fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
print("held", flush=True)
sys.stdin.read()
"""


def test_a_domain_held_by_another_run_is_skipped_and_freed_when_it_ends():
    a, b = [d for d in range(233, 240) if _free(d)][:2]   # ids no test run uses
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, DOMAIN_LOCK_DIR, str(a)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert claim_domain(iter([a, b])) == b          # a is another run's
    finally:
        holder.communicate("")                          # the other run ends
    assert _free(a)                                     # and its domain is free again


def _free(domain_id) -> bool:
    """Whether another process could claim ``domain_id`` now (asked in a new process:
    this one's own locks do not count against itself)."""
    probe = ("import fcntl, os, sys; fh = open(os.path.join(sys.argv[1], sys.argv[2] + "
             "'.lock'), 'a'); fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)")
    os.makedirs(DOMAIN_LOCK_DIR, exist_ok=True)
    return subprocess.run([sys.executable, "-c", probe, DOMAIN_LOCK_DIR, str(domain_id)],
                          capture_output=True).returncode == 0
