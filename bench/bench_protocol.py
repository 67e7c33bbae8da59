#!/usr/bin/env python3
# SPDX-License-Identifier: Apache-2.0
"""Throughput of the protocol core: frames/s and bytes/s through StreamDecoder (and the encoder).

Workload: PACKET frames of 4 x N int16 samples (default N = 400, i.e. 3228 bytes per
frame) with a STATUS heartbeat every 1000 packets, decoded from

* clean:      the error-free stream, in reads of 4 KiB (a typical serial read size),
              64 KiB, and one byte at a time (worst case for the Python loop, fewer frames);
* corrupted:  the same stream with 1 % of the frames hit by a random bit flip and
              random garbage (0..64 bytes) between 1 % of the frames, in 4 KiB reads;
* adversarial: a fake header (valid header CRC) claiming 64 KiB before EVERY frame, in
              4 KiB and 64 KiB reads (the contract: >= 50 % of the clean throughput);
              and a flood of nothing but such fake headers (no valid frame at all).

``--faults`` instead measures the recovery of a real FingertipLink from a simulated
fingertip over a pty (device reset mid-frame, garbage-only device, unplug, repeated
frames, stuck TCP client) and writes bench/results/protocol_faults.json.

Each figure is the best of ``--repeats`` runs (least disturbed by other processes on
the machine). Writes bench/results/protocol.json and prints a summary.

    python3 bench/bench_protocol.py [--packets 20000] [--samples 400] [--repeats 3]
    python3 bench/bench_protocol.py --faults [--trials 3]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import struct
import sys
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ae_tactile.link import FingertipLink, LinkConfig  # noqa: E402
from ae_tactile.protocol import (  # noqa: E402
    MAX_PAYLOAD_LEN,
    SYNC,
    DeviceState,
    FrameEncoder,
    Packet,
    Status,
    StreamDecoder,
)
from ae_tactile.virtual_device import (  # noqa: E402
    DeviceRunner,
    PtyTransport,
    TcpTransport,
    VirtualFingertip,
)


def make_frames(n_packets: int, n_samples: int, seed: int = 1) -> list[bytes]:
    rng = np.random.default_rng(seed)
    enc = FrameEncoder()
    noise = rng.integers(-2048, 2048, size=(16, 4, n_samples), dtype=np.int16)
    status = Status(
        uptime_us=0,
        state=DeviceState.TRIGGERED,
        sample_rate_hz=10_000_000,
        v_per_count=1e-6,
        threshold_counts=200,
        packet_samples=n_samples,
        pre_trigger=n_samples // 4,
        error_bits=0,
        device_dropped=0,
        firmware_version=(1, 0, 0),
        serial_number="AE-BENCH-0001",
    )
    frames = []
    t_us = 0
    for k in range(n_packets):
        t_us += 100
        if k % 1000 == 0:
            frames.append(enc.encode(status, t_us & 0xFFFFFFFF))
        pkt = Packet(
            noise[k % 16],
            10_000_000,
            1e-6,
            first_sample_index=k * 1000,
            pre_trigger=n_samples // 4,
            onset_index=n_samples // 4,
        )
        frames.append(enc.encode(pkt, t_us & 0xFFFFFFFF))
    return frames


def corrupt(frames: list[bytes], seed: int = 2) -> tuple[bytes, int, int]:
    """1 % of frames get one bit flip, 1 % of gaps get 0..64 garbage bytes."""
    rng = np.random.default_rng(seed)
    parts = []
    n_flipped = 0
    for f in frames:
        if rng.random() < 0.01:
            b = bytearray(f)
            bit = int(rng.integers(len(b) * 8))
            b[bit // 8] ^= 1 << (bit % 8)
            f = bytes(b)
            n_flipped += 1
        parts.append(f)
        if rng.random() < 0.01:
            parts.append(rng.integers(0, 256, int(rng.integers(0, 65)), dtype=np.uint8).tobytes())
    return b"".join(parts), n_flipped, len(frames)


def fake_header(seq: int) -> bytes:
    """A header with a valid header CRC claiming MAX_PAYLOAD_LEN (64 KiB) of payload."""
    head = struct.pack("<4sBBBBIII", SYNC, 1, 1, 0, 0, MAX_PAYLOAD_LEN, seq, 0)
    return head + struct.pack("<I", zlib.crc32(head))


def run_decoder(stream: bytes, chunk: int, repeats: int) -> dict:
    best = None
    for _ in range(repeats):
        dec = StreamDecoder()
        mv = memoryview(stream)
        n_frames = 0
        t0 = time.perf_counter()
        for i in range(0, len(stream), chunk):
            n_frames += len(dec.feed(mv[i : i + chunk]))
        n_frames += len(dec.flush())
        dt = time.perf_counter() - t0
        if best is None or dt < best[0]:
            best = (dt, n_frames, dec.stats())
    dt, n_frames, stats = best
    return {
        "chunk_bytes": chunk,
        "seconds": dt,
        "frames": n_frames,
        "frames_per_s": n_frames / dt,
        "bytes_per_s": len(stream) / dt,
        "mbytes_per_s": len(stream) / dt / 1e6,
        "stats": stats,
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--packets", type=int, default=20000)
    ap.add_argument("--samples", type=int, default=400, help="samples per channel per packet")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--faults", action="store_true", help="measure fault recovery instead")
    ap.add_argument("--trials", type=int, default=3, help="trials per fault (--faults)")
    ap.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parent / "results" / "protocol.json"
    )
    args = ap.parse_args(argv)
    if args.faults:
        return bench_faults(args.trials, args.out.parent / "protocol_faults.json")

    # encoder throughput
    best_enc = None
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        frames = make_frames(args.packets, args.samples)
        dt = time.perf_counter() - t0
        best_enc = dt if best_enc is None else min(best_enc, dt)
    stream = b"".join(frames)
    frame_bytes = len(frames[1])
    results = {
        "workload": {
            "packets": args.packets,
            "samples_per_channel": args.samples,
            "packet_frame_bytes": frame_bytes,
            "total_frames": len(frames),
            "stream_bytes": len(stream),
        },
        "encode": {
            "seconds": best_enc,
            "frames_per_s": len(frames) / best_enc,
            "note": "Packet construction (validation) + encode_frame, numpy samples",
        },
        "decode_clean": {},
    }
    for chunk in (4096, 65536):
        r = run_decoder(stream, chunk, args.repeats)
        assert r["frames"] == len(frames), (r["frames"], len(frames))
        results["decode_clean"][f"chunk_{chunk}"] = r
    n_small = min(len(frames), 1000)
    small = b"".join(frames[:n_small])
    r = run_decoder(small, 1, 1)
    assert r["frames"] == n_small
    results["decode_clean"]["chunk_1"] = r

    bad_stream, n_flipped, n_total = corrupt(frames)
    r = run_decoder(bad_stream, 4096, args.repeats)
    r["frames_bit_flipped"] = n_flipped
    r["frames_expected"] = n_total - n_flipped
    results["decode_corrupted"] = r

    adv = b"".join(fake_header(k) + f for k, f in enumerate(frames))
    results["decode_adversarial"] = {}
    for chunk in (4096, 65536):
        r = run_decoder(adv, chunk, args.repeats)
        assert r["frames"] == len(frames), (r["frames"], len(frames))
        clean = results["decode_clean"][f"chunk_{chunk}"]
        r["ratio_to_clean_bytes_per_s"] = r["bytes_per_s"] / clean["bytes_per_s"]
        r["ratio_to_clean_frames_per_s"] = r["frames_per_s"] / clean["frames_per_s"]
        r["note"] = "a fake 64 KiB header (valid header CRC) before every frame"
        results["decode_adversarial"][f"chunk_{chunk}"] = r
    flood = b"".join(fake_header(k) for k in range(2 * 65588 // 24 * 8))
    r = run_decoder(flood, 4096, 1)
    r["note"] = "nothing but fake 64 KiB headers, back to back (no valid frame)"
    results["decode_fake_header_flood"] = r

    results["load_average"] = os.getloadavg()
    results["environment"] = {
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "machine": platform.machine(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "note": "shared 2-core machine; best of repeats",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")

    print(
        f"workload: {n_total} frames ({args.packets} PACKETs of 4 x {args.samples} int16,"
        f" {frame_bytes} B each), {len(stream) / 1e6:.1f} MB"
    )
    print(f"encode:           {results['encode']['frames_per_s']:9.0f} frames/s")
    for name, r in results["decode_clean"].items():
        print(
            f"decode {name:10s} {r['frames_per_s']:9.0f} frames/s  {r['mbytes_per_s']:7.1f} MB/s"
        )
    r = results["decode_corrupted"]
    print(
        f"decode corrupted  {r['frames_per_s']:9.0f} frames/s  {r['mbytes_per_s']:7.1f} MB/s"
        f"  ({r['frames']} of {r['frames_expected']} intact frames decoded;"
        f" crc_errors {r['stats']['crc_errors']}, header_errors {r['stats']['header_errors']},"
        f" dropped {r['stats']['dropped_frames']})"
    )
    for name, r in results["decode_adversarial"].items():
        print(
            f"decode fake-64k {name:10s} {r['frames_per_s']:9.0f} frames/s"
            f"  {r['mbytes_per_s']:7.1f} MB/s  ({100 * r['ratio_to_clean_bytes_per_s']:.0f} %"
            f" of clean; truncated {r['stats']['truncated_frames']},"
            f" crc_errors {r['stats']['crc_errors']})"
        )
    r = results["decode_fake_header_flood"]
    print(
        f"decode fake-header flood  {r['mbytes_per_s']:7.2f} MB/s (no valid frame;"
        f" truncated {r['stats']['truncated_frames']}, crc_errors {r['stats']['crc_errors']})"
    )
    print(f"wrote {args.out}")
    return results


# ---------------------------------------------------------------------- faults
def _wait(cond, timeout_s: float, poll=None) -> float | None:
    """Seconds until cond() (polling every ms), or None after timeout_s."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if poll is not None:
            poll()
        if cond():
            return time.monotonic() - t0
        time.sleep(0.001)
    return None


def bench_faults(trials: int, out: Path) -> dict:
    """Recovery times of a real FingertipLink from injected faults (pty / TCP)."""
    root = Path(__file__).resolve().parents[1]
    with open(root / "config" / "scenes" / "random_touches.yaml") as fh:
        scene = dict(yaml.safe_load(fh), duration_s=12.0, name="long")
    res: dict = {"trials": trials}

    def rig(tmp, transport=None, **kw):
        dev = VirtualFingertip(scene, record=True)
        tr = transport or PtyTransport(str(Path(tmp) / "tip"))
        runner = DeviceRunner(dev, tr)
        link = FingertipLink(LinkConfig(port=tr.port, **kw), clock_ns=time.monotonic_ns)
        records = []
        runner.start()
        link.start()

        def poll():
            for b in link.poll():
                records.extend(b.packets)

        # configured and acquiring: the first packet is in
        ready = _wait(lambda: link.stats()["state"] == "connected" and records, 30, poll)
        assert ready is not None
        _wait(lambda: False, 0.3, poll)
        return dev, runner, link, records, poll

    def close(runner, link):
        link.stop()
        runner.stop()

    def add(name, key, value):
        res.setdefault(name, {}).setdefault(key, []).append(value)

    def since(t0, cond, timeout_s, poll):
        dt = _wait(cond, timeout_s, poll)
        return None if dt is None else time.monotonic() - t0

    def one_trial() -> None:
        with tempfile.TemporaryDirectory() as tmp:
            dev, runner, link, records, poll = rig(tmp)
            # 1. watchdog reset mid-frame (8192-sample PACKET cut in half), port open
            n0 = len(records)
            d0 = link.stats()["disconnects"]
            t0 = time.monotonic()
            runner.call(dev.reset_mid_frame, time.monotonic_ns())
            add(
                "reset_mid_frame",
                "boot_frame_delivered_s",
                since(t0, lambda: link.stats()["device_restarts_handled"] >= 1, 30, poll),
            )
            add(
                "reset_mid_frame", "first_packet_s", since(t0, lambda: len(records) > n0, 30, poll)
            )
            s = link.stats()
            add("reset_mid_frame", "disconnects", s["disconnects"] - d0)
            add("reset_mid_frame", "truncated_frames", s["truncated_frames"])
            # 2. repeated frames
            runner.call(dev.repeat_next, 5)
            _wait(lambda: link.stats()["duplicate_frames"] >= 5, 30, poll)
            s = link.stats()
            add("repeated_frames", "duplicates", s["duplicate_frames"])
            add("repeated_frames", "restarts_handled_extra", s["device_restarts_handled"] - 1)
            # 3. garbage only (wrong baud rate)
            t0 = time.monotonic()
            dev.garble(True)
            add(
                "garbage_only",
                "not_connected_after_s",
                since(t0, lambda: link.stats()["state"] != "connected", 30, poll),
            )
            _wait(lambda: False, 1.0, poll)
            dev.garble(False)
            n0 = len(records)
            t0 = time.monotonic()
            add(
                "garbage_only",
                "connected_again_s",
                since(t0, lambda: link.stats()["state"] == "connected", 30, poll),
            )
            add(
                "garbage_only",
                "first_packet_again_s",
                since(t0, lambda: len(records) > n0, 30, poll),
            )
            # 4. unplug for 1 s
            c0 = link.stats()["connects"]
            runner.unplug(1.0)
            t0 = time.monotonic()
            add(
                "unplug_1s",
                "not_connected_after_s",
                since(t0, lambda: link.stats()["state"] != "connected", 30, poll),
            )
            add(
                "unplug_1s",
                "connected_again_after_unplug_s",
                since(
                    t0,
                    lambda: link.stats()["connects"] > c0 and link.stats()["state"] == "connected",
                    30,
                    poll,
                ),
            )
            close(runner, link)
        # 5. a stuck TCP client next to the driver
        tr = TcpTransport(idle_timeout_s=5.0, client_sndbuf=4096)
        stuck = socket.create_connection((tr.host, int(tr.port.rsplit(":", 1)[1])))
        stuck.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        dev, runner, link, records, poll = rig(None, transport=tr)
        runner.call(dev.inject_garbage, bytes(300_000))
        t0 = time.monotonic()
        add("stuck_tcp_client", "dropped_after_s", since(t0, lambda: tr.timed_out >= 1, 60, poll))
        add("stuck_tcp_client", "driver_disconnects", link.stats()["disconnects"])
        close(runner, link)
        stuck.close()

    for _ in range(trials):
        one_trial()
    summary = {}
    for name, d in res.items():
        if isinstance(d, dict):
            summary[name] = {
                k: {
                    "median": float(np.median([v for v in vals if v is not None]))
                    if any(v is not None for v in vals)
                    else None,
                    "max": max((v for v in vals if v is not None), default=None),
                    "values": vals,
                }
                for k, vals in d.items()
            }
    summary["trials"] = trials
    summary["load_average"] = os.getloadavg()
    summary["link_defaults"] = {
        "link_timeout_s": 3.0,
        "stall_report_s": 0.25,
        "reconnect_initial_s": 0.2,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(summary, indent=2) + "\n")
    for name, d in summary.items():
        if isinstance(d, dict) and name != "link_defaults":
            print(name, {k: v["median"] for k, v in d.items()})
    print(f"wrote {out}")
    return summary


if __name__ == "__main__":
    main()
