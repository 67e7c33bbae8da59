# SPDX-License-Identifier: Apache-2.0
"""RViz markers: the fingertip sphere, the PVDF matrix, recent events and emissions as fading
spheres, the current contacts.

Each event (ContactEvent) or emission (Emission) is drawn as a sphere at its position, 2
sigma across (largest principal axis of its covariance, at least 0.3 mm), coloured by type
(an emission by its reading), fading out over its lifetime. Each current contact
(`contact_markers`) is a translucent disc-like sphere 1.5 mm across coloured by its state,
labelled with its id. Markers
carry a lifetime, so RViz removes them by itself; no TF is needed beyond the fingertip
frame (use it as RViz's fixed frame, or publish a static transform to the hand).
"""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.msg import ContactEvent, ContactState, Emission

#: RGB per event type.
EVENT_COLORS = {
    ContactEvent.TOUCH: (0.1, 0.8, 0.2),
    ContactEvent.DETOUCH: (0.2, 0.4, 1.0),
    ContactEvent.SLIP_PRECURSOR: (1.0, 0.6, 0.0),
    ContactEvent.SLIP: (1.0, 0.1, 0.1),
    ContactEvent.TEXTURE: (0.7, 0.2, 0.9),
}
#: RGB per emission reading (an emission's marker; the events' colours where they agree).
READING_COLORS = {
    Emission.UNKNOWN: (0.6, 0.6, 0.6),
    Emission.TOUCH: EVENT_COLORS[ContactEvent.TOUCH],
    Emission.RELEASE: EVENT_COLORS[ContactEvent.DETOUCH],
    Emission.MICRO_SLIP: EVENT_COLORS[ContactEvent.SLIP_PRECURSOR],
    Emission.SLIP: EVENT_COLORS[ContactEvent.SLIP],
    Emission.TEXTURE: EVENT_COLORS[ContactEvent.TEXTURE],
}
#: RGB per contact state (a current contact's marker).
STATE_COLORS = {
    ContactState.NO_CONTACT: (0.6, 0.6, 0.6),
    ContactState.STICK: (0.1, 0.8, 0.2),
    ContactState.INCIPIENT_SLIP: (1.0, 0.6, 0.0),
    ContactState.GROSS_SLIP: (1.0, 0.1, 0.1),
}
#: [m] diameter of a current contact's marker (about a fingertip contact's size)
CONTACT_MARKER_M = 1.5e-3


def _duration(seconds: float) -> Duration:
    sec = int(seconds)
    return Duration(sec=sec, nanosec=int((seconds - sec) * 1e9))


def sensor_markers(geometry: FingertipGeometry, frame_id: str, stamp) -> MarkerArray:
    """The sensing sphere (translucent) and the four PVDF elements (static, no lifetime)."""
    arr = MarkerArray()
    sphere = Marker()
    sphere.header.frame_id, sphere.header.stamp = frame_id, stamp
    sphere.ns, sphere.id, sphere.type, sphere.action = (
        "ae_tactile/fingertip",
        0,
        Marker.SPHERE,
        Marker.ADD,
    )
    d = 2.0 * geometry.radius_m
    sphere.scale.x = sphere.scale.y = sphere.scale.z = d
    sphere.pose.orientation.w = 1.0
    sphere.color = ColorRGBA(r=0.9, g=0.85, b=0.75, a=0.25)
    arr.markers.append(sphere)
    a = geometry.element_offset_m
    for k, (x, y, _) in enumerate(geometry.element_positions_m):
        m = Marker()
        m.header.frame_id, m.header.stamp = frame_id, stamp
        m.ns, m.id, m.type, m.action = "ae_tactile/pvdf", k, Marker.CUBE, Marker.ADD
        m.pose.position.x, m.pose.position.y = float(x), float(y)
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = 1.8 * a
        m.scale.z = 0.2e-3
        m.color = ColorRGBA(r=0.3, g=0.3, b=0.3, a=0.9)
        arr.markers.append(m)
    return arr


def contact_markers(contacts, frame_id: str, stamp, lifetime_s: float = 0.5) -> MarkerArray:
    """The current contacts (`ae_tactile.records.ContactSnapshot` or Contact messages): a
    sphere coloured by the contact's state and a text with its id, each living
    ``lifetime_s`` [s] (refreshed while the contact lasts)."""
    arr = MarkerArray()
    for c in contacts:
        cid = int(getattr(c, "contact_id", getattr(c, "id", 0)))
        if hasattr(c, "point_m"):
            x, y, z = (float(v) for v in c.point_m)
        else:
            x, y, z = c.position.x, c.position.y, c.position.z
        for kind in (Marker.SPHERE, Marker.TEXT_VIEW_FACING):
            m = Marker()
            m.header.frame_id, m.header.stamp = frame_id, stamp
            m.ns = "ae_tactile/contacts" if kind == Marker.SPHERE else "ae_tactile/contact_ids"
            m.id, m.type, m.action = cid, kind, Marker.ADD
            m.pose.position = Point(x=x, y=y, z=z)
            m.pose.orientation.w = 1.0
            r, g, b = STATE_COLORS.get(int(c.state), (1.0, 1.0, 1.0))
            if kind == Marker.SPHERE:
                m.scale.x = m.scale.y = m.scale.z = CONTACT_MARKER_M
                m.color = ColorRGBA(r=r, g=g, b=b, a=0.4)
            else:
                m.pose.position.z = z + CONTACT_MARKER_M
                m.scale.z = 0.8e-3  # [m] text height
                m.text = str(cid)
                m.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=0.9)
            m.lifetime = _duration(lifetime_s)
            arr.markers.append(m)
    return arr


class EventMarkers:
    """Keeps the recent events (ContactEvent) and emissions (Emission) and renders them as
    fading spheres."""

    def __init__(
        self,
        frame_id: str,
        lifetime_s: float = 2.0,
        max_events: int = 64,
        namespace: str = "ae_tactile/events",
    ):
        self.frame_id = frame_id
        self.lifetime_s = float(lifetime_s)
        self.max_events = int(max_events)
        self.namespace = namespace
        self.events: list[tuple[int, ContactEvent]] = []  # (received ns, event)
        self._next_id = 0

    def add(self, event: ContactEvent, now_ns: int) -> None:
        self.events.append((now_ns, event))
        if len(self.events) > self.max_events:
            del self.events[: len(self.events) - self.max_events]

    def render(self, now_ns: int, stamp) -> MarkerArray:
        arr = MarkerArray()
        keep = []
        for i, (t_ns, ev) in enumerate(self.events):
            age = (now_ns - t_ns) * 1e-9
            if age > self.lifetime_s:
                continue
            keep.append((t_ns, ev))
            cov = np.asarray(ev.position_covariance, dtype=float).reshape(3, 3)
            sigma = (
                float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (cov + cov.T)).max(), 0.0)))
                if np.all(np.isfinite(cov))
                else 0.0
            )
            size = max(4.0 * sigma, 0.3e-3)  # 2 sigma radius -> diameter 4 sigma
            m = Marker()
            m.header.frame_id, m.header.stamp = self.frame_id or ev.header.frame_id, stamp
            m.ns, m.id, m.type, m.action = self.namespace, i, Marker.SPHERE, Marker.ADD
            m.pose.position = Point(x=ev.position.x, y=ev.position.y, z=ev.position.z)
            m.pose.orientation.w = 1.0
            m.scale.x = m.scale.y = m.scale.z = size
            if isinstance(ev, Emission):
                r, g, b = READING_COLORS.get(ev.reading, (1.0, 1.0, 1.0))
            else:
                r, g, b = EVENT_COLORS.get(ev.event_type, (1.0, 1.0, 1.0))
            m.color = ColorRGBA(r=r, g=g, b=b, a=float(max(0.05, 1.0 - age / self.lifetime_s)))
            m.lifetime = _duration(max(self.lifetime_s - age, 0.05))
            arr.markers.append(m)
        self.events = keep
        # No DELETE markers: every marker carries its remaining lifetime, RViz drops it.
        return arr
