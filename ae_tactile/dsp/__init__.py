# SPDX-License-Identifier: Apache-2.0
"""Packet detection on the 4-channel stream (pure Python: numpy/scipy, never rclpy).

- `PacketDetector` / `DetectorConfig`: streaming band-pass, noise-floor tracking,
  threshold trigger with hysteresis and AE timing rules (HDT/HLT), overlapping-emission
  re-triggers, AIC onset refinement, windows [onset - pre, onset + post) of the original
  samples, saturation and per-packet noise; output `PacketBatch`, counters `DetectorStats`.
- `analyze_window`: the same per-packet fields for windows the device already cut
  (PACKET frames).
- Building blocks: `design_bandpass_sos`, `StreamingSOS` (filters), `BlockNoiseTracker`
  (noise), `aic_pick` (onset), `window_features` (features). Analytic test streams with
  exact onsets are evaluation code: `ae_eval.synth` in bench/.

See docs/detection.md.
"""
from .batch import PacketBatch
from .config import DetectorConfig, SampleParams
from .detector import DetectorStats, PacketDetector
from .features import window_features
from .filters import StreamingSOS, design_bandpass_sos, noise_power_gain
from .noise import BlockNoiseTracker
from .onset import aic_pick
from .windows import analyze_window

__all__ = [
    "PacketDetector", "DetectorConfig", "SampleParams", "DetectorStats", "PacketBatch",
    "analyze_window", "window_features", "design_bandpass_sos", "StreamingSOS",
    "noise_power_gain", "BlockNoiseTracker", "aic_pick",
]
