"""End-to-end latency and sustained packet rate of the composed system (bench/results/system.json).

1. Floor: two rclpy hops with an empty message (std_msgs/Empty ping -> pong), measured
   in the same process and run as the pipeline: what any rclpy pipeline pays at least.
2. Latency: emission (ground-truth time of the touch) -> ContactEvent received by a
   subscriber, through sim_fingertip (own process, pty) -> driver -> localizer, for a
   sparse random-touch scene; median and p99.
3. Sustained rate: random touches at increasing rates; for each, packets published by
   the driver, localized, dropped, and whether the latency stays bounded (no backlog).

Run: make bench-system
"""
from __future__ import annotations

import json
import os
import platform
import sys
import tempfile
import time

import numpy as np
import yaml

ROOT = os.environ.get("AE_TACTILE_ROOT", os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def two_hop_floor(n=400):
    import rclpy
    from rclpy.experimental import EventsExecutor
    from std_msgs.msg import Empty
    a, b = rclpy.create_node("bench_ping"), rclpy.create_node("bench_pong")
    ex = EventsExecutor()
    ex.add_node(a)
    ex.add_node(b)
    pong_pub = b.create_publisher(Empty, "bench/pong", 10)
    b.create_subscription(Empty, "bench/ping", lambda m: pong_pub.publish(Empty()), 10)
    got = []
    a.create_subscription(Empty, "bench/pong", lambda m: got.append(time.perf_counter_ns()), 10)
    ping_pub = a.create_publisher(Empty, "bench/ping", 10)
    t_end = time.monotonic() + 5
    while (ping_pub.get_subscription_count() < 1 or pong_pub.get_subscription_count() < 1) and time.monotonic() < t_end:
        ex.spin_once(timeout_sec=0.05)
    rtts = []
    for _ in range(n):
        t0 = time.perf_counter_ns()
        k = len(got)
        ping_pub.publish(Empty())
        while len(got) == k:
            ex.spin_once(timeout_sec=0.1)
        rtts.append((got[-1] - t0) * 1e-6)
    ex.shutdown()
    a.destroy_node()
    b.destroy_node()
    r = np.array(rtts[20:])
    return {"median_ms": float(np.median(r)), "p99_ms": float(np.percentile(r, 99)), "n": int(r.size)}


def run_scene(path):
    from ae_tactile.ros.bringup import Bringup, parse_args
    system = Bringup(parse_args(["--scene", path, "--monitor"]))
    system.monitor.print_live = False
    t0 = time.monotonic()
    system.spin(-1.0, drain_timeout_s=20.0)
    wall = time.monotonic() - t0
    s = system.monitor.summary()
    lat = np.array([(x.received_ns - x.stamp_ns) * 1e-6 for x in system.monitor.contacts])
    out = {"wall_s": wall, "truth": s["emissions"]["truth"], "localized": s["emissions"]["matched"],
           "driver_published": system.driver.published_packets,
           "driver_dropped": system.driver.link.packets_dropped(),
           "localizer_packets": system.localizer.counts["packets"],
           "rejected": {k: v for k, v in system.localizer.counts.items() if k.startswith("rejected_")},
           "latency_ms": {"median": float(np.median(lat)), "p99": float(np.percentile(lat, 99)),
                          "first_quarter_median": float(np.median(lat[: max(1, lat.size // 4)])),
                          "last_quarter_median": float(np.median(lat[-max(1, lat.size // 4):]))}
           if lat.size else {}}
    system.close()
    return out


def scene_with_rate(tmp, rate_hz, duration_s):
    with open(os.path.join(ROOT, "config", "scenes", "random_touches.yaml")) as fh:
        spec = yaml.safe_load(fh)
    spec["duration_s"] = duration_s
    spec["params"]["rate_hz"] = rate_hz
    spec["params"]["hold_min_s"], spec["params"]["hold_max_s"] = 0.002, 0.01
    path = os.path.join(tmp, f"rate_{rate_hz}.yaml")
    with open(path, "w") as fh:
        yaml.safe_dump(spec, fh)
    return path


def main() -> int:
    import rclpy
    os.environ.setdefault("ROS_DOMAIN_ID", "78")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    sys.setswitchinterval(0.0002)
    rclpy.init()
    rates = [int(r) for r in os.environ.get("AE_BENCH_RATES", "25,100,200,400").split(",")]
    out = {"machine": platform.platform(), "cpus": os.cpu_count()}
    try:
        out["two_hop_floor"] = two_hop_floor()
        print(f"two rclpy hops, empty message: median {out['two_hop_floor']['median_ms']:.3f} ms, "
              f"p99 {out['two_hop_floor']['p99_ms']:.3f} ms", flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            out["latency_sparse"] = run_scene(scene_with_rate(tmp, 20, 5.0))
            la = out["latency_sparse"]["latency_ms"]
            print(f"emission -> ContactEvent (20 touches/s): median {la['median']:.2f} ms, p99 {la['p99']:.2f} ms",
                  flush=True)
            out["rates"] = []
            for rate in rates:
                r = run_scene(scene_with_rate(tmp, rate, 3.0))
                r["touch_rate_hz"] = rate
                r["emission_rate_hz"] = r["truth"] / 3.0
                out["rates"].append(r)
                la = r["latency_ms"]
                print(f"{r['emission_rate_hz']:6.0f} emissions/s: {r['localized']}/{r['truth']} localized, "
                      f"driver dropped {r['driver_dropped']}, latency median {la.get('median', float('nan')):.1f} ms "
                      f"(first quarter {la.get('first_quarter_median', float('nan')):.1f}, last "
                      f"{la.get('last_quarter_median', float('nan')):.1f}), wall {r['wall_s']:.1f} s", flush=True)
    finally:
        rclpy.try_shutdown()
    os.makedirs(os.path.join(ROOT, "bench", "results"), exist_ok=True)
    with open(os.path.join(ROOT, "bench", "results", "system.json"), "w") as fh:
        json.dump(out, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
