#!/usr/bin/env python3
"""Throughput of the protocol core: frames/s and bytes/s through StreamDecoder (and the encoder).

Workload: PACKET frames of 4 x N int16 samples (default N = 400, i.e. 3228 bytes per
frame) with a STATUS heartbeat every 1000 packets, decoded from

* clean:      the error-free stream, in reads of 4 KiB (a typical serial read size),
              64 KiB, and one byte at a time (worst case for the Python loop, fewer frames);
* corrupted:  the same stream with 1 % of the frames hit by a random bit flip and
              random garbage (0..64 bytes) between 1 % of the frames, in 4 KiB reads.

Each figure is the best of ``--repeats`` runs (least disturbed by other processes on
the machine). Writes bench/results/protocol.json and prints a summary.

    python3 bench/bench_protocol.py [--packets 20000] [--samples 400] [--repeats 3]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ae_tactile.protocol import (DeviceState, FrameEncoder, Packet, Status,  # noqa: E402
                                 StreamDecoder)


def make_frames(n_packets: int, n_samples: int, seed: int = 1) -> list[bytes]:
    rng = np.random.default_rng(seed)
    enc = FrameEncoder()
    noise = rng.integers(-2048, 2048, size=(16, 4, n_samples), dtype=np.int16)
    status = Status(uptime_us=0, state=DeviceState.TRIGGERED, sample_rate_hz=10_000_000,
                    v_per_count=1e-6, threshold_counts=200, packet_samples=n_samples,
                    pre_trigger=n_samples // 4, error_bits=0, device_dropped=0,
                    firmware_version=(1, 0, 0), serial_number="AE-BENCH-0001")
    frames = []
    t_us = 0
    for k in range(n_packets):
        t_us += 100
        if k % 1000 == 0:
            frames.append(enc.encode(status, t_us & 0xFFFFFFFF))
        pkt = Packet(noise[k % 16], 10_000_000, 1e-6, first_sample_index=k * 1000,
                     pre_trigger=n_samples // 4, onset_index=n_samples // 4)
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


def run_decoder(stream: bytes, chunk: int, repeats: int) -> dict:
    best = None
    for _ in range(repeats):
        dec = StreamDecoder()
        mv = memoryview(stream)
        n_frames = 0
        t0 = time.perf_counter()
        for i in range(0, len(stream), chunk):
            n_frames += len(dec.feed(mv[i:i + chunk]))
        n_frames += len(dec.flush())
        dt = time.perf_counter() - t0
        if best is None or dt < best[0]:
            best = (dt, n_frames, dec.stats())
    dt, n_frames, stats = best
    return {"chunk_bytes": chunk, "seconds": dt, "frames": n_frames,
            "frames_per_s": n_frames / dt, "bytes_per_s": len(stream) / dt,
            "mbytes_per_s": len(stream) / dt / 1e6, "stats": stats}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--packets", type=int, default=20000)
    ap.add_argument("--samples", type=int, default=400, help="samples per channel per packet")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).resolve().parent / "results" / "protocol.json")
    args = ap.parse_args(argv)

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
        "workload": {"packets": args.packets, "samples_per_channel": args.samples,
                     "packet_frame_bytes": frame_bytes, "total_frames": len(frames),
                     "stream_bytes": len(stream)},
        "encode": {"seconds": best_enc, "frames_per_s": len(frames) / best_enc,
                   "note": "Packet construction (validation) + encode_frame, numpy samples"},
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

    results["environment"] = {
        "python": sys.version.split()[0], "numpy": np.__version__,
        "machine": platform.machine(), "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(), "note": "shared 2-core machine; best of repeats",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")

    print(f"workload: {n_total} frames ({args.packets} PACKETs of 4 x {args.samples} int16,"
          f" {frame_bytes} B each), {len(stream) / 1e6:.1f} MB")
    print(f"encode:           {results['encode']['frames_per_s']:9.0f} frames/s")
    for name, r in results["decode_clean"].items():
        print(f"decode {name:10s} {r['frames_per_s']:9.0f} frames/s  {r['mbytes_per_s']:7.1f} MB/s")
    r = results["decode_corrupted"]
    print(f"decode corrupted  {r['frames_per_s']:9.0f} frames/s  {r['mbytes_per_s']:7.1f} MB/s"
          f"  ({r['frames']} of {r['frames_expected']} intact frames decoded;"
          f" crc_errors {r['stats']['crc_errors']}, header_errors {r['stats']['header_errors']},"
          f" dropped {r['stats']['dropped_frames']})")
    print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main()
