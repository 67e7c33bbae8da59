# SPDX-License-Identifier: Apache-2.0
"""A virtual fingertip: firmware model speaking protocol v1 for a simulated scene.

`VirtualFingertip` is the device side of the serial link, transport-agnostic and
clock-driven: ``receive(bytes, now_ns)`` takes host bytes (commands) and
``poll(now_ns)`` returns the device bytes due by ``now_ns`` (ACKs, a STATUS heartbeat
every second, PACKET frames in triggered mode, STREAM blocks in stream mode).
`DeviceRunner` moves those bytes over a pseudo-terminal or a TCP port in real time
(or at a speed factor), so the driver cannot tell it from hardware.

Modules: `firmware` (the device model and its clock), `faults` (fault injection for
tests), `scene_spec` (the scene it plays), `transports` (`PtyTransport`,
`TcpTransport`), `runner` (`DeviceRunner`, the real-time loop).
"""

from .faults import FaultInjection
from .firmware import FIRMWARE_VERSION, TruthEvent, VirtualFingertip
from .runner import DeviceRunner
from .scene_spec import load_scene_spec
from .transports import LOG, PtyTransport, TcpTransport

__all__ = [
    "FIRMWARE_VERSION",
    "LOG",
    "DeviceRunner",
    "FaultInjection",
    "PtyTransport",
    "TcpTransport",
    "TruthEvent",
    "VirtualFingertip",
    "load_scene_spec",
]
