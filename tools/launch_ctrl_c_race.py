#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""Reproduce launch's own Ctrl-C race (no ROS node, none of ae_tactile's code).

`LaunchService.run_async` lets Ctrl-C's KeyboardInterrupt surface anywhere in its loop
and answers it with `except KeyboardInterrupt: continue`. When it lands while
`loop.create_task(self._process_one_event())` is scheduling the new task, the task is
never scheduled; when it is garbage-collected asyncio reports "Task was destroyed but it
is pending!" to the loop's exception handler, and run_async's handler sets the return
code to 1. The launched processes still stop cleanly.

The window is a few microseconds, so plain runs hit it about once in several hundred
Ctrl-Cs. `--widen` slows asyncio's `call_soon` by 1 ms to make it likely; every exit
code 1 then carries that message (the slowed call_soon also loses other callbacks
when the interrupt lands in them: launch then never exits, counted as 'no exit').
Usage (with ROS's environment, e.g. tools/run.sh):

    python tools/launch_ctrl_c_race.py [--runs 30] [--widen]
"""
import argparse
import os
import random
import signal
import subprocess
import sys
import time

RACE_MESSAGE = "Task was destroyed but it is pending!"


def child(widen: bool) -> int:
    """One launch of a chatty process (a line every 2 ms); return launch's exit code."""
    if widen:
        import asyncio.base_events as base_events

        call_soon = base_events.BaseEventLoop.call_soon

        def slow_call_soon(self, *args, **kwargs):
            time.sleep(1e-3)
            return call_soon(self, *args, **kwargs)

        base_events.BaseEventLoop.call_soon = slow_call_soon
    from launch import LaunchDescription, LaunchService
    from launch.actions import ExecuteProcess

    chatty = "import time\nwhile True:\n    print('x' * 40, flush=True)\n    time.sleep(0.002)"
    service = LaunchService()
    service.include_launch_description(
        LaunchDescription([ExecuteProcess(cmd=[sys.executable, "-u", "-c", chatty])])
    )
    return service.run()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--widen", action="store_true", help="slow call_soon by 1 ms")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        return child(a.widen)
    counts = {"exit 0": 0, "exit 1 with the race message": 0, "other": 0, "no exit": 0}
    for _ in range(a.runs):
        cmd = [sys.executable, __file__, "--child"] + (["--widen"] if a.widen else [])
        # SIGINT back to its default even when this script runs as a background job
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        time.sleep(1.0 + random.random())
        os.killpg(proc.pid, signal.SIGINT)                 # Ctrl-C: the whole group
        try:
            out, _ = proc.communicate(timeout=8)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            counts["no exit"] += 1
            continue
        if proc.returncode == 0 and RACE_MESSAGE not in out:
            counts["exit 0"] += 1
        elif proc.returncode == 1 and RACE_MESSAGE in out:
            counts["exit 1 with the race message"] += 1
        else:
            counts["other"] += 1
            print(f"exit {proc.returncode}:\n{out[-2000:]}")
    print(", ".join(f"{k}: {v}" for k, v in counts.items()), f"(of {a.runs} Ctrl-Cs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
