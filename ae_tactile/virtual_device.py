# SPDX-License-Identifier: Apache-2.0
"""A virtual fingertip: firmware model speaking protocol v1 for a simulated scene.

`VirtualFingertip` is the device side of the serial link, transport-agnostic and
clock-driven: ``receive(bytes, now_ns)`` takes host bytes (commands) and
``poll(now_ns)`` returns the device bytes due by ``now_ns`` (ACKs, a STATUS heartbeat
every second, PACKET frames in triggered mode, STREAM blocks in stream mode).
`DeviceRunner` moves those bytes over a pseudo-terminal or a TCP port in real time
(or at a speed factor), so the driver cannot tell it from hardware.

Device model (documented in docs/protocol.md and docs/simulator.md):
* The device clock is the host's monotonic clock since the virtual boot, in us; the
  sample counter restarts at 0 on every START.
* The scene's timeline starts at the first START and runs at ``speed`` x real time;
  later STOP/START (or a re-plug, which reboots a bus-powered device) resume it where
  wall-clock time has got to: what happened while stopped is not captured.
* Triggered mode: one window per emission as an ideal trigger would cut it (the
  simulator's `TriggeredSource`, ``pre_trigger`` samples before the earliest arrival),
  sent once its last sample has been taken, if its peak |count| reaches the threshold.
* Fault injection for tests: `inject_garbage`, `corrupt_next` (flip one payload bit:
  the host sees a CRC error and a sequence gap), `drop_next` (sequence gap),
  `repeat_next` (a frame sent twice), `inject_frame` (any body, numbered like the rest),
  `reset_mid_frame` (a watchdog reset while a frame is on the wire, port left open),
  `garble` (every output byte replaced by noise, as a wrong baud rate would).
"""

from __future__ import annotations

import copy
import errno
import logging
import os
import select
import socket
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass

import numpy as np
import yaml

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
from ae_tactile.sim.scene import SceneError, load_scene
from ae_tactile.sim.stream import KINDS

LOG = logging.getLogger("ae_tactile.virtual_device")

FIRMWARE_VERSION = (0, 1, 0)


@dataclass
class TruthEvent:
    """Ground truth of one emission, timed on the device clock (ns since virtual boot).

    captured: a PACKET frame was (or will be) sent for it (False: below threshold or
    the device was not acquiring).
    """

    device_time_ns: int
    scene_time_ns: int
    kind: str
    point_m: np.ndarray
    amplitude_pa_m: float
    event_id: int
    captured: bool


def load_scene_spec(scene) -> dict:
    """A scene spec dict from a path, YAML text or dict (validated once by loading it).
    SceneError on anything that is not a valid scene (bad YAML, nesting too deep, ...)."""
    try:
        return _load_scene_spec(scene)
    except (RecursionError, yaml.YAMLError) as exc:
        raise SceneError(f"scene is not a valid scene file: {type(exc).__name__}") from None
    except OSError as exc:
        raise SceneError(f"scene cannot be read: {exc}") from None


def _load_scene_spec(scene) -> dict:
    if isinstance(scene, dict):
        spec = copy.deepcopy(scene)
    elif isinstance(scene, (str, os.PathLike)) and os.path.exists(str(scene)):
        with open(scene, encoding="utf-8") as fh:
            spec = yaml.safe_load(fh)
        if not isinstance(spec, dict):
            raise SceneError(f"scene file is not a YAML mapping: {scene}")
        spec.setdefault("name", os.path.splitext(os.path.basename(str(scene)))[0])
    else:
        spec = yaml.safe_load(scene) if isinstance(scene, str) and "\n" in scene else None
        if not isinstance(spec, dict):
            raise SceneError(f"scene file not found or not a YAML mapping: {scene!r}")
    load_scene(copy.deepcopy(spec))  # validate now: clear errors before anything runs
    return spec


class VirtualFingertip:
    """Firmware model for one simulated fingertip (see the module docstring)."""

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
        self.sent_log: list[
            tuple
        ] = []  # (kind, seq, body, 'sent'|'dropped'|'corrupted') if record
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
        self._corrupt = 0
        self._drop = 0
        self._repeat = 0
        self._pending = None  # triggered mode: packets of the source not yet served
        self._exhausted = False
        self.garbled = False
        self._garble_rng = np.random.default_rng(12345)
        self.boot()

    # ------------------------------------------------------------------ power
    def boot(self) -> None:
        """(Re)boot: clock from 0, BOOT flag on the first frame, idle, nothing queued."""
        self.boot_ns = int(self.clock_ns())
        self.encoder = FrameEncoder(boot=True)
        self.decoder = StreamDecoder(direction=Direction.HOST_TO_DEVICE)
        self.state = DeviceState.IDLE
        self.out = bytearray()
        self._next_status_ns = self.boot_ns
        self._source = None
        self.boots = getattr(self, "boots", -1) + 1

    def device_us(self, now_ns: int) -> int:
        return (int(now_ns) - self.boot_ns) // 1000

    # ------------------------------------------------------------------ faults
    def inject_garbage(self, data: bytes) -> None:
        self.out += bytes(data)

    def corrupt_next(self, n: int = 1) -> None:
        self._corrupt += int(n)

    def drop_next(self, n: int = 1) -> None:
        self._drop += int(n)

    def repeat_next(self, n: int = 1) -> None:
        """The next n PACKET/STREAM frames are sent twice (byte-identical)."""
        self._repeat += int(n)

    def inject_frame(self, body, now_ns: int) -> None:
        """Send any frame body now, numbered and stamped like the device's own frames."""
        self._send(body, int(now_ns), "injected")

    def reset_mid_frame(
        self, now_ns: int, n_samples: int = MAX_SAMPLES, fraction: float = 0.5
    ) -> int:
        """A watchdog reset while a PACKET of ``n_samples`` is on the wire: its first
        ``fraction`` goes out, then the device reboots (the port stays open; the host sees
        the rebooted device's BOOT frame and heartbeats next). Returns the bytes cut off."""
        body = Packet(
            np.zeros((4, int(n_samples)), np.int16), self.sample_rate_hz, self.v_per_count
        )
        frame = self.encoder.encode(body, self.device_us(now_ns) & 0xFFFFFFFF)
        cut = frame[: max(24, int(len(frame) * float(fraction)))]
        pending = bytes(self.out)
        self.boot()
        self.out += pending + cut
        return len(frame) - len(cut)

    def garble(self, on: bool = True) -> None:
        """Replace every output byte by noise (a wrong baud rate) until garble(False)."""
        self.garbled = bool(on)

    # ------------------------------------------------------------------ framing
    def _send(self, body, device_time_ns: int, kind: str) -> None:
        ts_us = ((int(device_time_ns) - self.boot_ns) // 1000) & 0xFFFFFFFF
        seq = self.encoder.next_seq
        data = self.encoder.encode(body, ts_us)
        fate = "sent"
        if kind in ("packet", "stream") and self._drop > 0:
            self._drop -= 1
            fate = "dropped"
        elif kind in ("packet", "stream") and self._corrupt > 0:
            self._corrupt -= 1
            data = bytearray(data)
            data[len(data) // 2] ^= 0x10  # a payload bit: frame CRC fails
            fate = "corrupted"
        if self.record:
            self.sent_log.append((kind, seq, body, fate))
        if fate == "dropped":
            return
        self.out += data
        if kind in ("packet", "stream") and fate == "sent" and self._repeat > 0:
            self._repeat -= 1
            self.out += data  # the same frame, byte for byte, again
            self.frames_repeated = getattr(self, "frames_repeated", 0) + 1
        if fate == "sent" and kind in self.frames_sent:
            self.frames_sent[kind] += 1

    def status(self, now_ns: int) -> Status:
        return Status(
            uptime_us=self.device_us(now_ns),
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

    # ------------------------------------------------------------------ commands
    def receive(self, data: bytes, now_ns: int) -> None:
        """Host bytes in: decode commands, apply them, queue ACKs (and STATUS)."""
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
        offset = int(
            np.ceil(self.scene_at_start_ns * 1e-9 * fs)
        )  # scene sample at device sample 0
        self.index_offset = offset
        if mode == AcqMode.STREAM:
            self._source = scene.streaming_source(start_index=offset)
        else:
            self._source = scene.triggered_source(
                pretrigger_s=self.pre_trigger / fs, window_s=self.packet_samples / fs
            )
            self._skip_before_ns = self.scene_at_start_ns
            self._interf = None
            self._interf_pending = []
            from ae_tactile.sim.interference import InterferenceSource, scene_bursts

            if scene_bursts(scene.process.scene_truth()):
                # electrical bursts of the scene: common-mode packets on the same stream
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
        """All device bytes due by host time now_ns."""
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
        if self.garbled and out:
            out = self._garble_rng.integers(0, 256, len(out), dtype=np.uint8).tobytes()
        return out

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
            counts = np.clip(np.rint(samples / self.v_per_count), -self.adc_max - 1, self.adc_max)
            body = Packet(
                counts.astype(np.int16),
                fs,
                self.v_per_count,
                first_sample_index=start_dev,
                pre_trigger=self.pre_trigger,
            )
            self._send(body, self._device_ns_of_sample(start_dev), "packet")
            self.interference_packets_sent += 1
        self._interf_pending = keep

    interference_packets_sent = 0
    _interf = None

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
                em = batch.emissions
                t_scene = int(em.time_ns[i])
                start_dev = int(batch.start_index[i]) - self.index_offset
                last_ns = self._device_ns_of_sample(start_dev + self.packet_samples - 1)
                if t_scene >= self._skip_before_ns and last_ns > now_ns:
                    self._pending = (batch, i)
                    return
                self._serve(batch, i, t_scene, start_dev)
                i += 1
            self._pending = None

    def _serve(self, batch, i: int, t_scene: int, start_dev: int) -> None:
        em = batch.emissions
        captured = t_scene >= self._skip_before_ns and start_dev >= 0
        counts = np.clip(
            np.rint(batch.samples_v[i] / self.v_per_count), -self.adc_max - 1, self.adc_max
        )
        counts = counts.astype(np.int16)
        if captured and int(np.abs(counts).max()) < self.threshold_counts:
            captured = False
            self.packets_below_threshold += 1
        self.truth.append(
            TruthEvent(
                device_time_ns=self.device_ns_of_scene(t_scene),
                scene_time_ns=t_scene,
                kind=KINDS[int(em.kind[i])],
                point_m=np.array(em.point_m[i]),
                amplitude_pa_m=float(em.strength_pa_m[i]),
                event_id=int(em.event_id[i]),
                captured=captured,
            )
        )
        if not captured:
            return
        sat = np.abs(counts.astype(np.int32)) >= self.adc_max
        mask = int(sum(1 << k for k in range(4) if sat[k].any()))
        body = Packet(
            counts,
            self.sample_rate_hz,
            self.v_per_count,
            first_sample_index=start_dev,
            pre_trigger=self.pre_trigger,
            saturation_mask=mask,
        )
        self._send(body, self._device_ns_of_sample(start_dev), "packet")

    def _poll_stream(self, now_ns: int) -> None:
        n = self.stream_block_samples
        while True:
            dev_first = self._source.position - self.index_offset
            if self._device_ns_of_sample(dev_first + n - 1) > now_ns:
                return
            chunk = self._source.next_chunk(n)
            counts = np.clip(
                np.rint(chunk.samples_v / self.v_per_count), -self.adc_max - 1, self.adc_max
            )
            counts = counts.astype(np.int16)
            sat = np.abs(counts.astype(np.int32)) >= self.adc_max
            mask = int(sum(1 << k for k in range(4) if sat[k].any()))
            em = chunk.emissions
            for j in range(len(em)):
                t_scene = int(em.time_ns[j])
                self.truth.append(
                    TruthEvent(
                        device_time_ns=self.device_ns_of_scene(t_scene),
                        scene_time_ns=t_scene,
                        kind=KINDS[int(em.kind[j])],
                        point_m=np.array(em.point_m[j]),
                        amplitude_pa_m=float(em.strength_pa_m[j]),
                        event_id=int(em.event_id[j]),
                        captured=True,
                    )
                )
            self._send(
                StreamBlock(
                    counts,
                    self.sample_rate_hz,
                    self.v_per_count,
                    first_sample_index=dev_first,
                    saturation_mask=mask,
                ),
                self._device_ns_of_sample(dev_first),
                "stream",
            )

    def set_normal_load(self, load_n: float, now_ns: int) -> int:
        """Change the scene's normal load P (closed-loop grip) from the earliest scene time
        not yet produced, at or after now. Returns that scene time (ns). ValueError if the
        scene has no normal load or is not playing."""
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
            return self._pending is None and getattr(self, "_exhausted", False)
        return True

    def pop_truth(self) -> list[TruthEvent]:
        out = list(self.truth)
        self.truth.clear()
        return out


# ====================================================================== transports
class PtyTransport:
    """A pseudo-terminal pair in raw mode; the driver opens ``path`` (the slave side).

    ``link_path`` (optional) is a symlink kept pointing at the current slave, like a udev
    rule: `unplug()` closes the pty and removes it, `replug()` opens a new pty and puts it
    back. While unplugged nothing answers at ``link_path``: a driver retrying it cannot
    open another program's pty that reused the closed one's number (/dev/pts/N).
    """

    def __init__(self, link_path: str | None = None):
        self.link_path = link_path
        self.master = self.slave = None
        self.path = None
        self.replug()

    def replug(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        if self.link_path:
            tmp = f"{self.link_path}.tmp{os.getpid()}"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self.path, tmp)
            os.replace(tmp, self.link_path)

    def unplug(self) -> None:
        if self.link_path and os.path.islink(self.link_path):
            os.unlink(self.link_path)  # first: the number of the pty closed next is free
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None

    @property
    def port(self) -> str:
        return self.link_path or self.path

    def fileno(self):
        return self.master

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: no reader attached yet
            if exc.errno == errno.EIO:
                return b""
            raise

    def write(self, data: memoryview) -> int:
        try:
            return os.write(self.master, data)
        except BlockingIOError:
            return 0

    def connected(self) -> bool:
        return self.master is not None

    def close(self) -> None:
        self.unplug()


class _TcpClient:
    __slots__ = ("sock", "out", "last_progress", "address")

    def __init__(self, sock, address, now: float):
        self.sock, self.address, self.out, self.last_progress = sock, address, bytearray(), now


class TcpTransport:
    """A TCP server on ``host:port`` (127.0.0.1 unless told otherwise; port 0 picks one);
    the driver opens ``socket://host:port``.

    Several clients at once (up to ``max_clients``; one more is accepted and closed at
    once, counted in ``refused``). Each client gets every device byte sent after it
    connected, through its own buffer of at most ``max_client_buffer`` bytes; commands
    from any client reach the device. A client that takes no byte for ``idle_timeout_s``
    while bytes wait for it, or whose buffer overflows, is disconnected (``timed_out``,
    ``overflowed``): a client that connects and never reads cannot lock the others out
    nor make the device's memory grow.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        max_clients: int = 4,
        idle_timeout_s: float = 5.0,
        max_client_buffer: int = 4 << 20,
        client_sndbuf: int | None = None,
    ):
        if int(max_clients) < 1 or not idle_timeout_s > 0 or int(max_client_buffer) < 1:
            raise ValueError("need max_clients >= 1, idle_timeout_s > 0, max_client_buffer >= 1")
        self.host = host
        self._port = port
        self.max_clients = int(max_clients)
        self.idle_timeout_s = float(idle_timeout_s)
        self.max_client_buffer = int(max_client_buffer)
        self.client_sndbuf = client_sndbuf
        self.listener = None
        self.clients: list[_TcpClient] = []
        self.accepted = self.refused = self.timed_out = self.overflowed = 0
        self.replug()

    def replug(self) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((self.host, self._port))
        self._port = self.listener.getsockname()[1]
        self.listener.listen(16)
        self.listener.setblocking(False)

    def unplug(self) -> None:
        for c in self.clients:
            c.sock.close()
        self.clients = []
        if self.listener is not None:
            self.listener.close()
        self.listener = None

    @property
    def conn(self):
        """The first client's socket (None without clients)."""
        return self.clients[0].sock if self.clients else None

    @property
    def port(self) -> str:
        return f"socket://{self.host}:{self._port}"

    def fileno(self):
        return self.listener.fileno() if self.listener is not None else None

    def filenos(self) -> list[int]:
        """Descriptors to wait on: the listener and every client."""
        if self.listener is None:
            return []
        return [self.listener.fileno()] + [c.sock.fileno() for c in self.clients]

    def _drop(self, c: _TcpClient, why: str) -> None:
        LOG.info("virtual device: client %s disconnected (%s)", c.address, why)
        try:
            c.sock.close()
        except OSError:
            pass
        self.clients.remove(c)

    def _accept(self) -> None:
        while self.listener is not None:
            try:
                sock, address = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if len(self.clients) >= self.max_clients:
                self.refused += 1  # accepted and closed: a clean refusal
                sock.close()
                continue
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self.client_sndbuf:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, int(self.client_sndbuf))
            self.clients.append(_TcpClient(sock, address, time.monotonic()))
            self.accepted += 1

    def read(self) -> bytes:
        """Accept new clients; the bytes (commands) every client sent, concatenated."""
        self._accept()
        data = []
        for c in list(self.clients):
            try:
                got = c.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                got = b""
            if not got:  # the client closed
                self._drop(c, "closed by the client")
                continue
            data.append(got)
        return b"".join(data)

    def write(self, data: memoryview) -> int:
        """Queue the device bytes for every client and send what they take; all consumed."""
        data = bytes(data)
        for c in list(self.clients):
            if len(c.out) + len(data) > self.max_client_buffer:
                self._drop(c, f"more than {self.max_client_buffer} bytes waiting")
                self.overflowed += 1  # counted once gone: never counted and still listed
                continue
            c.out += data
        self.service()
        return len(data)

    def service(self) -> None:
        """Send what each client takes; disconnect the ones stuck for idle_timeout_s."""
        now = time.monotonic()
        for c in list(self.clients):
            if c.out:
                try:
                    n = c.sock.send(c.out)
                except (BlockingIOError, InterruptedError):
                    n = 0
                except OSError:
                    self._drop(c, "send failed")
                    continue
                if n:
                    del c.out[:n]
                    c.last_progress = now
            else:
                c.last_progress = now
            if c.out and now - c.last_progress > self.idle_timeout_s:
                self._drop(c, f"took no byte for {self.idle_timeout_s:g} s")
                self.timed_out += 1  # counted once gone: never counted and still listed

    def connected(self) -> bool:
        return self.listener is not None

    def close(self) -> None:
        self.unplug()


class DeviceRunner:
    """Real-time loop moving bytes between a VirtualFingertip and a transport (thread).

    Writes never block the loop (pending bytes wait for the reader); the outgoing buffer
    is bounded like a device's transmit queue (``max_out_bytes``; overflow = frames lost).
    """

    def __init__(
        self,
        device: VirtualFingertip,
        transport,
        *,
        period_s: float = 0.0005,
        max_out_bytes: int = 8 << 20,
    ):
        self.device = device
        self.transport = transport
        self.period_s = period_s
        self.max_out_bytes = max_out_bytes
        self._out = bytearray()
        self._stop = threading.Event()
        self._lock = threading.RLock()
        self._callers = 0  # threads waiting in call(): the loop stays out of the lock
        self._callers_lock = threading.Lock()
        self._unplugged_until = None
        self.out_overflow_bytes = 0
        self.thread = threading.Thread(
            target=self._run, name="ae_tactile_virtual_device", daemon=True
        )

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        """Stop the loop (if it was started: a node stopped while it was being built
        never started it) and close the transport."""
        self._stop.set()
        if self.thread.ident is not None:
            self.thread.join(2.0)
        self.transport.close()

    def call(self, fn, *args):
        """Run fn(*args) while the device loop is held (for changes from other threads).

        The device loop takes its lock again right after each short wait, so a caller that
        merely waited for the lock could starve on a busy machine (a grip command applied
        seconds late): the caller raises a flag that the loop honours by staying out of the
        lock until the call is done."""
        with self._callers_lock:  # "+= 1" is not atomic between threads
            self._callers += 1
        try:
            with self._lock:
                return fn(*args)
        finally:
            with self._callers_lock:
                self._callers -= 1

    @property
    def pending_out_bytes(self) -> int:
        """Bytes the device produced that the transport has not taken yet."""
        return len(self._out)

    def unplug(self, duration_s: float) -> None:
        """Pull the cable for duration_s: transport closed, device unpowered; then re-plug,
        which boots the device again (bus powered), as real USB hardware would."""
        with self._lock:
            self.transport.unplug()
            self._out.clear()
            self._unplugged_until = time.monotonic() + float(duration_s)

    def _run(self) -> None:
        dev = self.device
        while not self._stop.is_set():
            while self._callers and not self._stop.is_set():
                time.sleep(0.0001)  # another thread is waiting for the lock: let it in
            with self._lock:
                if self._unplugged_until is not None:
                    if time.monotonic() < self._unplugged_until:
                        pass
                    else:
                        self._unplugged_until = None
                        self.transport.replug()
                        dev.boot()
                if self._unplugged_until is None and self.transport.connected():
                    now = int(dev.clock_ns())
                    try:
                        data = self.transport.read()
                    except OSError:
                        data = b""
                    if data:
                        dev.receive(data, now)
                    new = dev.poll(now)
                    if new:
                        if len(self._out) + len(new) > self.max_out_bytes:
                            self.out_overflow_bytes += len(new)
                        else:
                            self._out += new
                    if self._out:
                        try:
                            n = self.transport.write(memoryview(self._out))
                        except OSError:
                            n = len(self._out)
                        del self._out[:n]
                    if hasattr(self.transport, "service"):
                        self.transport.service()
                fds = []
                if self.transport.connected():
                    fds = (
                        self.transport.filenos()
                        if hasattr(self.transport, "filenos")
                        else [self.transport.fileno()]
                    )
                    fds = [fd for fd in fds if fd is not None]
            if fds and not self._out:
                try:
                    select.select(fds, [], [], self.period_s)
                except (OSError, ValueError):
                    time.sleep(self.period_s)
            else:
                time.sleep(self.period_s / 4 if self._out else self.period_s)
