# SPDX-License-Identifier: Apache-2.0
"""`grip_reflex` (example hand-side node): squeeze harder when the fingertip feels slip coming.

On every SLIP_PRECURSOR (or SLIP) event on `slip`, the commanded grip force on
`grip_force_command` (std_msgs/Float64, N) is multiplied by ``gain`` (up to
``max_force_n``), at most once per ``refractory_s``. The reaction time from the
precursor's emission stamp to the command is logged and kept (`reactions_ms`), with the
contact that slipped. The contacts held come from `contacts` (TOUCH when a contact begins,
DETOUCH when it ends, with its id): a slip event of a contact that already ended is
ignored (its object was let go). It is a documented example of closing the loop, not a
grasp controller: a real hand would feed the command to its force controller.
"""

from __future__ import annotations

import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from std_msgs.msg import Float64

from ae_tactile.msg import ContactEvent
from ae_tactile.ros.conversions import time_msg_to_ns
from ae_tactile.ros.node_utils import LATCHED, run_node
from ae_tactile.ros.params import Param, declare, tunable

REFLEX_PARAMS = [
    Param("initial_force_n", 1.0, "Grip force before any reflex", 0.0, 1000.0),
    tunable(Param("gain", 1.6, "Factor applied to the force on a slip precursor", 1.0, 100.0)),
    tunable(Param("max_force_n", 5.0, "Largest force the reflex commands", 0.0, 1000.0)),
    tunable(Param("refractory_s", 0.05, "Shortest time between two force increases", 0.0, 10.0)),
    Param("diagnostics_period_s", 1.0, "Period of /diagnostics messages", 0.05, 60.0),
]


class GripReflexNode(Node):
    def __init__(self, **kwargs):
        super().__init__("grip_reflex", **kwargs)
        self.p = declare(self, REFLEX_PARAMS)
        self.force_n = self.p["initial_force_n"]
        self.last_ns = None
        self.reactions_ms: list[float] = []
        self.commands: list[tuple[int, float]] = []  # (ROS ns, N)
        # Latched: the command is a state (the force to hold), so a hand controller or the
        # simulated fingertip that subscribes late still gets the latest one.
        self.pub = self.create_publisher(Float64, "grip_force_command", LATCHED)
        self.create_subscription(ContactEvent, "slip", self.on_slip, 100)
        self.create_subscription(ContactEvent, "contacts", self.on_contact, 100)
        self.held: set[int] = set()  # ids of the contacts begun and not ended
        self.ended: set[int] = set()  # ids of the contacts that ended
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(self.p["diagnostics_period_s"], self.publish_diagnostics)

    def publish_diagnostics(self) -> None:
        st = DiagnosticStatus(
            level=DiagnosticStatus.OK,
            name=f"{self.get_fully_qualified_name()}: grip reflex",
            hardware_id="grip_force_command",
            message=f"commanding {self.force_n:.2f} N after {len(self.commands)} reflexes",
        )
        st.values = [
            KeyValue(key="force_n", value=f"{self.force_n:.3f}"),
            KeyValue(key="reflexes", value=str(len(self.commands))),
            KeyValue(key="contacts_held", value=" ".join(map(str, sorted(self.held)))),
        ]
        msg = DiagnosticArray(status=[st])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def on_contact(self, ev: ContactEvent) -> None:
        if ev.event_type == ContactEvent.TOUCH:
            self.held.add(int(ev.contact_id))
        elif ev.event_type == ContactEvent.DETOUCH:
            self.held.discard(int(ev.contact_id))
            self.ended.add(int(ev.contact_id))

    def on_slip(self, ev: ContactEvent) -> None:
        if ev.event_type not in (ContactEvent.SLIP_PRECURSOR, ContactEvent.SLIP):
            return
        if ev.contact_id in self.ended:  # its object was let go: nothing to hold
            return
        now = self.get_clock().now().nanoseconds
        if self.last_ns is not None and now - self.last_ns < self.p["refractory_s"] * 1e9:
            return
        new = min(self.force_n * self.p["gain"], self.p["max_force_n"])
        if new <= self.force_n:
            return
        self.force_n, self.last_ns = new, now
        self.pub.publish(Float64(data=float(new)))
        reaction = (now - time_msg_to_ns(ev.header.stamp)) * 1e-6
        self.reactions_ms.append(reaction)
        self.commands.append((now, new))
        kind = "slip precursor" if ev.event_type == ContactEvent.SLIP_PRECURSOR else "slip"
        self.get_logger().info(
            f"{kind} of contact {ev.contact_id} -> grip force {new:.2f} N ({reaction:.1f} ms "
            "after the emission)"
        )


def main(args=None) -> int:
    return run_node(GripReflexNode, args)


if __name__ == "__main__":
    sys.exit(main())
