# SPDX-License-Identifier: Apache-2.0
"""Device clock -> host (ROS) clock mapping, drift-robust, monotonic, re-syncing.

Each received frame gives a pair (d, h): d = device time of the frame (ns, from the
unwrapped microsecond counter), h = host receive time (ns). The host time is the
device time mapped through an affine clock model plus a non-negative transport
latency:

    h = h_ref + (d - d_ref) * (1 + skew) + offset + latency,   latency >= 0.

The latency (USB polling, OS scheduling) is positive and heavy-tailed, so the model is
fitted to the *lower envelope* of the offsets (h - d): the window of recent pairs is
split into buckets, each bucket keeps its minimum offset (the least-delayed frame), and
a line through those minima gives offset and skew (least squares, robust because each
minimum is already a near-zero-latency sample). Arrival time alone would carry all the
jitter; the lower envelope carries only the smallest latency.

Skew is only fitted over at least ``min_span_for_skew_s`` (10 s) and bounded by
``max_skew`` (200 ppm, several times a crystal's tolerance): a latency floor that rises
for a while (a loaded host) must not pass for clock drift.

Guarantees: mapped times never go backwards, whatever the device clock does (a would-be
step back is clamped and counted), also across a re-sync: the new model's outputs start
after the last output of the old one. One exception keeps stamps true: a packet whose
device time is at most ``reorder_s`` behind the latest one mapped (a window that started
before a packet sent earlier) keeps its own stamp. The model is rebuilt (counted as a re-sync) when

* device time goes back by more than ``max_backstep_s`` (a restarted device clock; the
  link also resets on the protocol's BOOT flag and passes a large ``max_backstep_s``,
  since its packets carry sample times older than the frames sent before them);
* a frame is earlier than the model by more than ``max_jump_s`` (the device clock stepped
  forward, the host clock back): at once, on that frame;
* ``step_frames`` frames in a row, over ``step_span_s`` of device time, are later than the
  model by more than ``step_back_s``, the first of them behind the latest device time by
  at least half its latency, and their latency does not fall (the device clock stepped
  back without a restart): a latency that large and that persistent is no transport delay,
  and no backlog read after a host stall either (its latency falls as fast as the device
  time advances). A reader that stays behind (a busy host) is as late for as long, but
  its device times go on: no step. The new model starts from those frames
  (``clock_steps`` counts these events).

The host clock stepping (the system clock, set by NTP) is the caller's to see, against a
monotonic clock: `shift_host` moves the model with it (``host_steps``).

The bucket minima are fitted robustly: a bucket whose minimum sits well above the line
(every frame of it delayed, e.g. behind a burst of garbage or a host stall) is left out
of the line, so it cannot pull the envelope late.
"""

from __future__ import annotations

from collections import deque

import numpy as np

#: A bucket minimum this far above the envelope line [ns] (or 3x the median distance,
#: if more) is a delayed bucket (every frame of it late: behind garbage, a host stall),
#: left out of the slope: transport jitter leaves bucket minima well within it.
DELAYED_BUCKET_NS = 1_000_000


def _envelope_slope(d: np.ndarray, off: np.ndarray) -> float:
    """Slope of the line through the bucket minima (device time d [ns], offset off [ns]),
    least squares refitted without the delayed buckets (at most 3 passes)."""
    keep = np.ones(len(d), dtype=bool)
    slope, intercept = np.polyfit(d, off, 1)
    for _ in range(3):
        r = off - (slope * d + intercept)
        r -= r[keep].min()
        now = r <= max(3.0 * float(np.median(r[keep])), DELAYED_BUCKET_NS)
        if now.sum() < 3 or np.array_equal(now, keep):
            break
        keep = now
        slope, intercept = np.polyfit(d[keep], off[keep], 1)
    return float(slope)


#: late frames in a row remembered for the step test (a long backlog keeps its newest)
_LATE_RUN_KEEP = 256


class DeviceClockMapper:
    """Map device timestamps (ns) to host timestamps (ns) through the lower envelope.

    Parameters
    ----------
    window_s : float
        Span of recent pairs the model is fitted to [s].
    bucket_s : float
        Width of one bucket of the lower envelope [s] (its minimum offset is kept).
    max_jump_s : float
        A frame earlier than the model by more than this [s] resets the model.
    min_span_for_skew_s : float
        Skew is fitted only over at least this span of device time [s].
    max_skew : float
        Bound of the fitted skew (dimensionless, 200e-6 = 200 ppm).
    max_backstep_s : float
        Device time going back by more than this [s] is a restarted device clock.
    step_back_s : float
        Latency above the model [s] that, ``step_frames`` frames in a row, means the clock
        stepped (device clock back or host clock forward); above any transport delay or
        host stall the link expects.
    step_frames : int
        Frames in a row needed to detect such a step (one delayed read is not one).
    step_span_s : float
        Device time [s] those frames must span, their latency not falling: a backlog read
        after a host stall is as late but its latency falls as fast as its device time
        advances (read in one go), a clock step's stays.
    reorder_s : float
        A device time at most this far [s] behind the latest one mapped is a packet out of
        order (e.g. a window that started before a packet sent earlier): it keeps its own
        stamp. Farther behind, it is a clock step not detected yet: held after the last
        output (counted in ``clamped``).
    """

    def __init__(
        self,
        window_s: float = 30.0,
        bucket_s: float = 0.5,
        max_jump_s: float = 0.25,
        min_span_for_skew_s: float = 10.0,
        max_skew: float = 200e-6,
        max_backstep_s: float = 1.0,
        step_back_s: float = 0.25,
        step_frames: int = 4,
        reorder_s: float = 0.05,
        step_span_s: float = 0.05,
    ):
        if not (window_s > 0 and bucket_s > 0 and bucket_s < window_s):
            raise ValueError("need 0 < bucket_s < window_s")
        if not (max_jump_s > 0 and min_span_for_skew_s > 0 and 0 <= max_skew < 0.01):
            raise ValueError(
                "max_jump_s and min_span_for_skew_s must be > 0, 0 <= max_skew < 0.01"
            )
        self.window_ns = int(window_s * 1e9)
        self.bucket_ns = int(bucket_s * 1e9)
        self.max_jump_ns = int(max_jump_s * 1e9)
        self.min_span_ns = int(min_span_for_skew_s * 1e9)
        self.max_skew = float(max_skew)
        if not (step_back_s > 0 and int(step_frames) >= 1):
            raise ValueError("step_back_s must be > 0 and step_frames >= 1")
        self.max_backstep_ns = int(max_backstep_s * 1e9)
        self.step_back_ns = int(step_back_s * 1e9)
        self.step_frames = int(step_frames)
        if not step_span_s >= 0:
            raise ValueError("step_span_s must be >= 0")
        self.step_span_ns = int(step_span_s * 1e9)
        if not reorder_s >= 0:
            raise ValueError("reorder_s must be >= 0")
        self.reorder_ns = int(reorder_s * 1e9)
        self._last_out_d: int | None = None  # the latest device time mapped [ns]
        self.resyncs = 0  # model resets (device restart, offset jump)
        self.clamped = 0  # outputs held back to stay monotonic
        self.steps = 0  # clock steps detected from a persistent latency (step_back_s)
        self.host_steps = 0  # host clock steps the caller reported (shift_host)
        self._floor_out: int | None = None  # last output of any model: outputs stay after it
        self.reset()
        self.resyncs = 0

    def reset(self) -> None:
        """Forget the model (next update starts a new one); counts as a re-sync."""
        self._buckets: deque[list[int]] = deque()  # [bucket_id, d_at_min, offset_min]
        self._d_ref: int | None = None
        self._last_d: int | None = None
        self._offset_ns = 0.0
        self._skew = 0.0
        #: (device ns, host ns, latency ns) of the frames in a row later than step_back_s
        self._late_run: list[tuple[int, int, int]] = []
        self.resyncs += 1

    @property
    def synced(self) -> bool:
        return self._d_ref is not None

    @property
    def skew(self) -> float:
        """Fitted d(h - d)/dd: host clock rate over device clock rate, minus 1."""
        return self._skew

    @property
    def device_rate_error(self) -> float:
        """Device clock rate error vs the host (e.g. +8e-5: device crystal 80 ppm fast)."""
        return -self._skew / (1.0 + self._skew)

    def update(self, device_ns: int, host_ns: int) -> bool:
        """Add one (device, host receive) pair.

        Parameters
        ----------
        device_ns : int
            Device time of the frame [ns].
        host_ns : int
            Host receive time of the frame [ns].

        Returns
        -------
        bool
            True if the model was reset by this pair (a restart or a clock jump).
        """
        device_ns = int(device_ns)
        host_ns = int(host_ns)
        did_reset = False
        if self._last_d is not None and device_ns < self._last_d - self.max_backstep_ns:
            # Frames carry sample times, so a packet's device time may precede frames sent
            # before it (by its window and the device's queue); a step back by more than
            # max_backstep_s is a restarted device clock.
            self.reset()
            did_reset = True
        elif self._d_ref is not None:
            # latency = host - model >= 0; a frame earlier than the model by more than
            # max_jump means a clock jumped (device time forward, host clock back): start over.
            latency = host_ns - self._predict(device_ns)
            if latency < -self.max_jump_ns:
                self.reset()
                did_reset = True
            elif latency > self.step_back_ns:
                if not self._late_run and self._last_d - device_ns < latency // 2:
                    # late, but the device time did not go back with it: a reader behind
                    # (a busy host), whose frames the envelope leaves out; no step
                    self._add(device_ns, host_ns)
                    return did_reset
                self._late_run.append((device_ns, host_ns, latency))
                del self._late_run[:-_LATE_RUN_KEEP]
                if self._late_run_is_a_step():
                    return self._restart_from_late_run()
            else:
                self._late_run.clear()
        self._add(device_ns, host_ns)
        return did_reset

    def _late_run_is_a_step(self) -> bool:
        """The late frames in a row are a clock step: at least step_frames of them over
        step_span of device time, their latency not falling by half that span (a backlog
        read after a host stall falls by all of it)."""
        run = self._late_run
        if len(run) < self.step_frames:
            return False
        span = run[-1][0] - run[0][0]
        return span >= self.step_span_ns and run[0][2] - run[-1][2] < 0.5 * span

    def _restart_from_late_run(self) -> bool:
        """A clock step: rebuild the model from the frames that showed it."""
        run = self._late_run
        self.reset()
        self.steps += 1
        for d, h, _ in run:
            self._add(d, h)
        return True

    def shift_host(self, step_ns: int) -> None:
        """The host clock stepped by ``step_ns`` [ns] (seen by the caller against a
        monotonic clock): the model moves with it, so the next stamps are in the host's new
        time (after a step back, held after the last one handed out until they pass it)."""
        step_ns = int(step_ns)
        self.host_steps += 1
        self._offset_ns += step_ns
        for b in self._buckets:
            b[2] += step_ns
        self._late_run = [(d, h + step_ns, lat) for d, h, lat in self._late_run]

    def _add(self, device_ns: int, host_ns: int) -> None:
        """One pair into the bucket minima (and the fit, when a minimum moved)."""
        if self._d_ref is None:
            self._d_ref = device_ns
        self._last_d = device_ns if self._last_d is None else max(self._last_d, device_ns)
        offset = host_ns - device_ns
        bucket = (device_ns - self._d_ref) // self.bucket_ns
        changed = False
        if self._buckets and self._buckets[-1][0] == bucket:
            if offset < self._buckets[-1][2]:
                self._buckets[-1][1:] = [device_ns, offset]
                changed = True
        else:
            self._buckets.append([bucket, device_ns, offset])
            changed = True
        oldest = bucket - self.window_ns // self.bucket_ns
        while self._buckets and self._buckets[0][0] < oldest:
            self._buckets.popleft()
            changed = True
        if changed:  # the envelope only moves when a bucket minimum does
            self._fit()

    def _fit(self) -> None:
        b = np.array(self._buckets, dtype=np.float64)
        d = b[:, 1] - self._d_ref
        off = b[:, 2]
        span = d[-1] - d[0] if len(d) > 1 else 0.0
        if len(d) >= 3 and span >= self.min_span_ns:
            # Line through the bucket minima, then lowered onto the envelope of the points
            # (the fitted line must not sit above any minimum: latency >= 0).
            slope = _envelope_slope(d, off)
            slope = float(np.clip(slope, -self.max_skew, self.max_skew))
            intercept = float(np.min(off - slope * d))
            self._skew, self._offset_ns = slope, intercept
        else:
            self._skew, self._offset_ns = 0.0, float(off.min())

    def _predict(self, device_ns: int) -> int:
        dd = device_ns - self._d_ref
        return device_ns + int(round(self._offset_ns + self._skew * dd))

    def to_host_ns(self, device_ns: int) -> int:
        """Host time of a device time; increasing from call to call (but for packets out of order).

        Parameters
        ----------
        device_ns : int
            Device time [ns].

        Returns
        -------
        int
            Host time [ns]; later than every one returned before (clamped and counted in
            ``clamped`` when the model would give an earlier one), except for a device time
            less than ``reorder_s`` behind the latest one mapped, which keeps its own.

        Raises
        ------
        RuntimeError
            Before the first `update`.
        """
        if self._d_ref is None:
            raise RuntimeError("DeviceClockMapper.to_host_ns called before any update()")
        device_ns = int(device_ns)
        out = self._predict(device_ns)
        last_d = self._last_out_d
        if last_d is not None and last_d - self.reorder_ns <= device_ns < last_d:
            return out  # a packet out of order: its own stamp (the outputs after it stay)
        # strictly after everything already handed out: across a re-sync, for a device time
        # far behind the last one (a clock step not detected yet)
        floor = self._floor_out
        if floor is not None and out <= floor:
            out = floor + 1
            self.clamped += 1
        self._floor_out = out
        self._last_out_d = device_ns
        return out
