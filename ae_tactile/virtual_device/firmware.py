# SPDX-License-Identifier: Apache-2.0
"""The firmware model: commands in, ACK / STATUS / PACKET / STREAM frames out, on a clock.

Device model (documented in docs/protocol.md and docs/simulator.md):

* The device clock is the host's monotonic clock since the virtual boot, in us; the
  sample counter restarts at 0 on every START.
* The scene's timeline starts at the first START and runs at ``speed`` x real time;
  later STOP/START (or a re-plug, which reboots a bus-powered device) resume it where
  wall-clock time has got to: what happened while stopped is not captured.
* Triggered mode: one window per emission as an ideal trigger would cut it (the
  simulator's `TriggeredSource`, ``pre_trigger`` samples before the earliest arrival),
  sent once its last sample has been taken, if its peak |count| reaches the threshold.
  A scene's electrical bursts come as common-mode packets on the same stream.
* Stream mode: blocks of ``stream_block_samples``, sent once their last sample is taken.
"""

from __future__ import annotations

import copy
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from ae_tactile.protocol import (
    MAX_SAMPLES,
    Ack,
    AckResult,
    AcqMode,
    Command,
    DeviceState,
    Direction,
    FrameEncoder,
    Opcode,
    Packet,
    Status,
    StreamBlock,
    StreamDecoder,
)
from ae_tactile.sim.interference import InterferenceSource, scene_bursts
from ae_tactile.sim.scene import load_scene
from ae_tactile.sim.stream import KINDS

from .faults import FaultInjection
from .scene_spec import load_scene_spec

FIRMWARE_VERSION = (0, 1, 0)


@dataclass
class TruthEvent:
    """Ground truth of one emission, timed on the device clock.

    Parameters
    ----------
    device_time_ns : int
        Host-clock time [ns] at which the emission is played.
    scene_time_ns : int
        Its time on the scene's timeline [ns].
    kind : str
        Emission kind (`ae_tactile.sim.stream.KINDS`).
    point_m : numpy.ndarray, shape (3,)
        Source point [m].
    amplitude_pa_m : float
        Source strength [Pa m].
    event_id : int
        The scene's event number.
    captured : bool
        A PACKET frame was (or will be) sent for it (False: below threshold, or the
        device was not acquiring).
    """

    device_time_ns: int
    scene_time_ns: int
    kind: str
    point_m: np.ndarray
    amplitude_pa_m: float
    event_id: int
    captured: bool


class VirtualFingertip(FaultInjection):
    """Firmware model for one simulated fingertip (see the module docstring).

    Transport-agnostic and clock-driven: `receive` takes host bytes (commands), `poll`
    returns the device bytes due by a host time; `DeviceRunner` moves them in real time.

    Parameters
    ----------
    scene : str, os.PathLike or dict
        Scene file, YAML text or spec (`load_scene_spec`).
    serial_number : str
        What STATUS reports (1..32 printable ASCII).
    speed : float
        Playback speed of the scene (1 = real time), in [0.001, 1000].
    packet_samples : int
        PACKET length N [samples], <= MAX_SAMPLES.
    pre_trigger : int
        Samples before the earliest arrival in a packet, < packet_samples.
    threshold_counts : int or None
        Trigger threshold [ADC counts]; None or 0: 6 noise sigma (at least 4).
    stream_block_samples : int
        Samples per channel of a STREAM block.
    clock_ns : callable
        The host's monotonic clock [ns].
    record : bool
        Keep every frame's fate in ``sent_log``: (kind, seq, body, 'sent' | 'dropped' |
        'corrupted'), and in ``sent_host_ns`` the host time [ns] its timestamp stands for
        (a packet's first sample).

    Raises
    ------
    ae_tactile.sim.scene.SceneError
        Not a valid scene.
    ValueError
        A setting out of its range.
    """

    #: interference packets sent so far (scenes with electrical bursts)
    interference_packets_sent = 0
    _interf = None  # the scene's interference source while acquiring triggered

    def __init__(
        self,
        scene,
        *,
        serial_number: str = "AE-SIM-0001",
        speed: float = 1.0,
        packet_samples: int = 400,
        pre_trigger: int = 80,
        threshold_counts: int | None = None,
        stream_block_samples: int = 2000,
        clock_ns=time.monotonic_ns,
        record: bool = False,
    ):
        self.spec = load_scene_spec(scene)
        if not (np.isfinite(speed) and 1e-3 <= speed <= 1e3):
            raise ValueError(f"speed must be in [0.001, 1000], got {speed}")
        if not 0 <= pre_trigger < packet_samples <= MAX_SAMPLES:
            raise ValueError("need 0 <= pre_trigger < packet_samples <= MAX_SAMPLES")
        if not 1 <= stream_block_samples <= MAX_SAMPLES:
            raise ValueError(f"stream_block_samples must be in [1, {MAX_SAMPLES}]")
        self.serial_number = serial_number
        self.speed = float(speed)
        self.clock_ns = clock_ns
        self.record = bool(record)
        self.sent_log: list[tuple] = []
        self.sent_host_ns: list[int] = []  # host clock [ns] each sent_log frame is stamped at
        self.packet_samples = int(packet_samples)
        self.pre_trigger = int(pre_trigger)
        self.stream_block_samples = int(stream_block_samples)
        scene0 = load_scene(copy.deepcopy(self.spec))
        self.sample_rate_hz = int(round(scene0.config.sample_rate_hz))
        self.v_per_count = float(np.float32(scene0.config.lsb_v))
        self.adc_max = (1 << (scene0.config.adc_bits - 1)) - 1
        self.duration_ns = int(scene0.duration_s * 1e9)
        noise_counts = scene0.noise_rms_v / scene0.config.lsb_v
        self.threshold_counts = (
            int(threshold_counts) if threshold_counts else int(max(4, np.ceil(6 * noise_counts)))
        )
        self.scene_t0_ns: int | None = None  # host clock at the first START
        self.scene_process = None  # exposed for closed-loop scenes
        self.truth: deque[TruthEvent] = deque()
        self.frames_sent = {"packet": 0, "stream": 0, "status": 0, "ack": 0}
        self.packets_below_threshold = 0
        self._init_faults()
        self._pending = None  # triggered mode: packets of the source not yet served
        self._exhausted = False
        self.boots = -1
        self.boot()

    # ------------------------------------------------------------------ power
    def boot(self) -> None:
        """(Re)boot: clock from 0, BOOT flag on the first frame, idle, nothing queued."""
        self.boot_ns = int(self.clock_ns())
        self.clock_step_ns = 0  # steps of the device clock (fault injection) [ns]
        self.encoder = FrameEncoder(boot=True)
        self.decoder = StreamDecoder(direction=Direction.HOST_TO_DEVICE)
        self.state = DeviceState.IDLE
        self.out = bytearray()
        self._next_status_ns = self.boot_ns
        self._source = None
        self.boots += 1

    def device_us(self, now_ns: int) -> int:
        """Device clock [us] at host time ``now_ns`` [ns]."""
        return (int(now_ns) - self.boot_ns + self.clock_step_ns) // 1000

    # ------------------------------------------------------------------ framing
    def _send(self, body, device_time_ns: int, kind: str) -> None:
        ts_us = self.device_us(device_time_ns) & 0xFFFFFFFF
        seq = self.encoder.next_seq
        data, fate = self._fate(kind, self.encoder.encode(body, ts_us))
        if self.record:
            self.sent_log.append((kind, seq, body, fate))
            self.sent_host_ns.append(int(device_time_ns))
        if fate == "dropped":
            return
        self.out += data
        if self._repeat_due(kind, fate):
            self.out += data  # the same frame, byte for byte, again
        if fate == "sent" and kind in self.frames_sent:
            self.frames_sent[kind] += 1

    def status(self, now_ns: int) -> Status:
        """The STATUS body at host time ``now_ns`` [ns]."""
        return Status(
            uptime_us=self.device_us(now_ns) % (1 << 64),  # a clock stepped below 0 wraps
            state=self.state,
            sample_rate_hz=self.sample_rate_hz,
            v_per_count=self.v_per_count,
            threshold_counts=self.threshold_counts,
            packet_samples=self.packet_samples,
            pre_trigger=self.pre_trigger,
            error_bits=0,
            device_dropped=0,
            firmware_version=FIRMWARE_VERSION,
            serial_number=self.serial_number,
        )

    def _to_counts(self, samples_v: np.ndarray) -> np.ndarray:
        """Volts -> int16 ADC counts, clipped to the ADC's range."""
        counts = np.clip(np.rint(samples_v / self.v_per_count), -self.adc_max - 1, self.adc_max)
        return counts.astype(np.int16)

    def _saturation_mask(self, counts: np.ndarray) -> int:
        """Bit k set if channel k reached the ADC rail."""
        sat = np.abs(counts.astype(np.int32)) >= self.adc_max
        return int(sum(1 << k for k in range(4) if sat[k].any()))

    def _truth(self, em, i: int, captured: bool) -> TruthEvent:
        """The ground truth of emission i of an emission list."""
        t_scene = int(em.time_ns[i])
        return TruthEvent(
            device_time_ns=self.device_ns_of_scene(t_scene),
            scene_time_ns=t_scene,
            kind=KINDS[int(em.kind[i])],
            point_m=np.array(em.point_m[i]),
            amplitude_pa_m=float(em.strength_pa_m[i]),
            event_id=int(em.event_id[i]),
            captured=captured,
        )

    # ------------------------------------------------------------------ commands
    def receive(self, data: bytes, now_ns: int) -> None:
        """Host bytes in: decode commands, apply them, queue ACKs (and STATUS).

        Parameters
        ----------
        data : bytes
            What the host sent, any chunking.
        now_ns : int
            Host time of arrival [ns].
        """
        for frame in self.decoder.feed(data):
            if isinstance(frame.body, Command):
                self._command(frame.body, int(now_ns))

    def _command(self, cmd: Command, now_ns: int) -> None:
        result, value = AckResult.OK, 0
        op = cmd.opcode
        if op == Opcode.START:
            running = {
                AcqMode.TRIGGERED: DeviceState.TRIGGERED,
                AcqMode.STREAM: DeviceState.STREAMING,
            }
            if self.state != running[cmd.mode]:  # START in the running mode: idempotent
                self._start(cmd.mode, now_ns)
            value = int(cmd.mode)
        elif op == Opcode.STOP:
            self.state = DeviceState.IDLE
            self._source = None
        elif op == Opcode.SET_THRESHOLD:
            self.threshold_counts = int(cmd.threshold_counts)
            value = self.threshold_counts
        elif op == Opcode.SET_SAMPLE_RATE:
            if self.state != DeviceState.IDLE:
                result = AckResult.BAD_STATE
            elif not 1_000_000 <= cmd.sample_rate_hz <= 20_000_000:
                result = AckResult.BAD_ARGUMENT
            else:
                self.sample_rate_hz = int(cmd.sample_rate_hz)
                value = self.sample_rate_hz
        elif op == Opcode.SET_PACKET_LENGTH:
            if self.state != DeviceState.IDLE:
                result = AckResult.BAD_STATE
            else:
                self.packet_samples, self.pre_trigger = int(cmd.n_samples), int(cmd.pre_trigger)
                value = self.packet_samples
        self._send(Ack(cmd.command_id, op, result, value), now_ns, "ack")
        if op == Opcode.GET_STATUS:
            self._send(self.status(now_ns), now_ns, "status")

    def _scene(self):
        spec = copy.deepcopy(self.spec)
        spec.setdefault("sensor", {})["sample_rate_hz"] = float(self.sample_rate_hz)
        return load_scene(spec)

    def _start(self, mode: AcqMode, now_ns: int) -> None:
        self._pending = None  # first, for finished() called from other threads
        self._exhausted = False
        if self.scene_t0_ns is None:
            self.scene_t0_ns = now_ns
        scene = self._scene()
        self.scene_process = scene.process
        fs = self.sample_rate_hz
        self.start_ns = now_ns  # sample 0 of this run
        self.scene_at_start_ns = int((now_ns - self.scene_t0_ns) * self.speed)
        self.mode = mode
        self.state = DeviceState.STREAMING if mode == AcqMode.STREAM else DeviceState.TRIGGERED
        # scene sample at device sample 0
        self.index_offset = int(np.ceil(self.scene_at_start_ns * 1e-9 * fs))
        if mode == AcqMode.STREAM:
            self._source = scene.streaming_source(start_index=self.index_offset)
            return
        self._source = scene.triggered_source(
            pretrigger_s=self.pre_trigger / fs, window_s=self.packet_samples / fs
        )
        self._skip_before_ns = self.scene_at_start_ns
        self._interf = None
        self._interf_pending = []
        if scene_bursts(scene.process.scene_truth()):
            # electrical bursts of the scene: common-mode packets on the same stream;
            # host clock at scene time 0 (shared-clock bursts: one source, every
            # simulated fingertip of this machine)
            t0 = self.start_ns - int(self.scene_at_start_ns / self.speed)
            self._interf = InterferenceSource(
                scene,
                pretrigger_s=self.pre_trigger / fs,
                window_s=self.packet_samples / fs,
                host_t0_ns=t0,
            )

    # ------------------------------------------------------------------ time
    def scene_ns(self, now_ns: int) -> int:
        """Scene time (ns) reached at host time now_ns (while playing)."""
        return int((now_ns - self.scene_t0_ns) * self.speed)

    def device_ns_of_scene(self, scene_ns: int) -> int:
        """Host-clock (ns) at which scene time scene_ns is played in the current run."""
        return self.start_ns + int((scene_ns - self.scene_at_start_ns) / self.speed)

    def _device_ns_of_sample(self, device_index: int) -> int:
        return self.start_ns + int(round(device_index * 1e9 / self.sample_rate_hz / self.speed))

    # ------------------------------------------------------------------ output
    def poll(self, now_ns: int) -> bytes:
        """All device bytes due by a host time.

        Parameters
        ----------
        now_ns : int
            Host time [ns].

        Returns
        -------
        bytes
            The frames (and injected faults) due: a STATUS every second, ACKs, PACKET
            frames whose window has been sampled, STREAM blocks.
        """
        now_ns = int(now_ns)
        if now_ns >= self._next_status_ns:
            self._send(self.status(now_ns), now_ns, "status")
            self._next_status_ns = now_ns + 1_000_000_000
        if self._source is not None:
            if self.state == DeviceState.TRIGGERED:
                self._poll_triggered(now_ns)
            elif self.state == DeviceState.STREAMING:
                self._poll_stream(now_ns)
        out, self.out = bytes(self.out), bytearray()
        return self._garbled(out)

    def _poll_interference(self, now_ns: int, horizon: int) -> None:
        """Serve the scene's interference packets whose window has closed by now_ns."""
        t_if, pk = self._interf.next_packets(horizon)
        for i in range(len(t_if)):
            self._interf_pending.append((int(t_if[i]), pk.samples_v[i]))
        keep = []
        fs = self.sample_rate_hz
        for t_scene, samples in self._interf_pending:
            start_dev = int(round(t_scene * fs / 1e9)) - self.pre_trigger - self.index_offset
            if self._device_ns_of_sample(start_dev + self.packet_samples - 1) > now_ns:
                keep.append((t_scene, samples))
                continue
            if t_scene < self._skip_before_ns or start_dev < 0:
                continue
            body = Packet(
                self._to_counts(samples),
                fs,
                self.v_per_count,
                first_sample_index=start_dev,
                pre_trigger=self.pre_trigger,
            )
            self._send(body, self._device_ns_of_sample(start_dev), "packet")
            self.interference_packets_sent += 1
        self._interf_pending = keep

    def _poll_triggered(self, now_ns: int) -> None:
        horizon = min(self.scene_ns(now_ns), self.duration_ns)  # the scene ends: silence
        if self._interf is not None:
            self._poll_interference(now_ns, horizon)
        while True:
            if self._pending is None:
                batch = self._source.next_packets(16, horizon_ns=horizon)
                if len(batch) == 0:
                    self._exhausted = horizon >= self.duration_ns
                    return
                self._pending = (batch, 0)
            batch, i = self._pending
            while i < len(batch):
                t_scene = int(batch.emissions.time_ns[i])
                start_dev = int(batch.start_index[i]) - self.index_offset
                last_ns = self._device_ns_of_sample(start_dev + self.packet_samples - 1)
                if t_scene >= self._skip_before_ns and last_ns > now_ns:
                    self._pending = (batch, i)
                    return
                self._serve(batch, i, t_scene, start_dev)
                i += 1
            self._pending = None

    def _serve(self, batch, i: int, t_scene: int, start_dev: int) -> None:
        captured = t_scene >= self._skip_before_ns and start_dev >= 0
        counts = self._to_counts(batch.samples_v[i])
        if captured and int(np.abs(counts).max()) < self.threshold_counts:
            captured = False
            self.packets_below_threshold += 1
        self.truth.append(self._truth(batch.emissions, i, captured))
        if not captured:
            return
        body = Packet(
            counts,
            self.sample_rate_hz,
            self.v_per_count,
            first_sample_index=start_dev,
            pre_trigger=self.pre_trigger,
            saturation_mask=self._saturation_mask(counts),
        )
        self._send(body, self._device_ns_of_sample(start_dev), "packet")

    def _poll_stream(self, now_ns: int) -> None:
        n = self.stream_block_samples
        while True:
            dev_first = self._source.position - self.index_offset
            if self._device_ns_of_sample(dev_first + n - 1) > now_ns:
                return
            chunk = self._source.next_chunk(n)
            counts = self._to_counts(chunk.samples_v)
            mask = self._saturation_mask(counts)
            em = chunk.emissions
            for j in range(len(em)):
                self.truth.append(self._truth(em, j, True))
            block = StreamBlock(
                counts,
                self.sample_rate_hz,
                self.v_per_count,
                first_sample_index=dev_first,
                saturation_mask=mask,
            )
            self._send(block, self._device_ns_of_sample(dev_first), "stream")

    # ------------------------------------------------------------------ scene
    def set_normal_load(self, load_n: float, now_ns: int) -> int:
        """Change the scene's normal load P (closed-loop grip).

        Parameters
        ----------
        load_n : float
            The new normal load [N].
        now_ns : int
            Host time [ns]; the change applies from the earliest scene time not yet
            produced, at or after it.

        Returns
        -------
        int
            The scene time [ns] the change applies from.

        Raises
        ------
        ValueError
            The scene has no normal load or is not playing.
        """
        proc = self.scene_process
        if proc is None or not hasattr(proc, "set_normal_load"):
            raise ValueError("this scene has no normal load to change (or is not playing)")
        at = max(self.scene_ns(now_ns), self._process_horizon_ns(proc))
        proc.set_normal_load(float(load_n), at)
        return at

    @staticmethod
    def _process_horizon_ns(proc) -> int:
        if hasattr(proc, "parts"):  # composite: the part timelines, shifted back
            return max(
                [
                    off + getattr(p, "horizon_ns", 0)
                    for off, p, _ in proc.parts
                    if hasattr(p, "horizon_ns")
                ]
                or [0]
            )
        return int(getattr(proc, "horizon_ns", 0))

    def finished(self, now_ns: int) -> bool:
        """True once the scene's duration has been played and, in triggered mode, every
        packet of it has been served (the device may lag real time on a loaded host).

        Safe without the runner's lock: `_exhausted` turns true only after the last packet
        was served, and `_pending` is cleared first when a scene starts."""
        if self.scene_t0_ns is None or self.scene_ns(now_ns) <= self.duration_ns + 50_000_000:
            return False
        if self.state == DeviceState.TRIGGERED:
            return self._pending is None and self._exhausted
        return True

    def pop_truth(self) -> list[TruthEvent]:
        """The ground truth gathered since the last call (oldest first)."""
        out = list(self.truth)
        self.truth.clear()
        return out
