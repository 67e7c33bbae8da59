# SPDX-License-Identifier: Apache-2.0
"""Shared pieces of the scene generators: seeded draws, contact-patch geometry on the
sphere, and emission lists built from event parameters.

Contact patches: a patch point at tangent-plane offset (u, v) from a contact centre c0 on
the sphere is (c0 + u e1 + v e2) R / |c0 + u e1 + v e2| (e1, e2 orthonormal, tangent).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.sim.emission_list import EmissionList

NS_PER_S = 1_000_000_000  # [ns/s]


def to_ns(t_s) -> np.ndarray:
    """Times [s] -> int64 [ns], rounded to the nearest nanosecond."""
    return np.round(np.asarray(t_s, dtype=float) * NS_PER_S).astype(np.int64)


def seeded_rng(seed, *keys) -> np.random.Generator:
    """A PCG64 generator of (scene seed, keys): each generator (and each part of one) draws
    from its own stream, so adding draws to one never changes another's."""
    return np.random.Generator(
        np.random.PCG64(np.random.SeedSequence([int(seed), *map(int, keys)]))
    )


def tangent_basis(center_m):
    """Orthonormal tangent vectors (e1, e2) at points (..., 3) of the sphere; e1 points
    along +x projected on the tangent plane (along +y... at the poles' degenerate case)."""
    c = np.asarray(center_m, dtype=float)
    n = c / np.linalg.norm(c, axis=-1, keepdims=True)
    ref = np.broadcast_to(np.array([1.0, 0.0, 0.0]), n.shape).copy()
    par = np.abs(n[..., 0]) > 0.9
    ref[par] = np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref * n).sum(-1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(n, e1)
    return e1, e2


def patch_points(geometry: FingertipGeometry, center_m, u_m, v_m) -> np.ndarray:
    """Points on the sphere at tangent-plane offsets (u, v) from one contact centre (3,)."""
    c = np.asarray(center_m, dtype=float)
    e1, e2 = tangent_basis(c)
    p = c + np.asarray(u_m, float)[..., None] * e1 + np.asarray(v_m, float)[..., None] * e2
    return p * (geometry.radius_m / np.linalg.norm(p, axis=-1, keepdims=True))


def uniform_disc(rng, n, r_in, r_out):
    """n points uniform (by area) in the annulus r_in <= r < r_out: (u, v)."""
    r = np.sqrt(rng.uniform(r_in**2, r_out**2, n))
    th = rng.uniform(0.0, 2.0 * np.pi, n)
    return r * np.cos(th), r * np.sin(th)


def check_patch(geometry, center, radius_m, what):
    """ValueError when a contact patch of ``radius_m`` [m] around ``center`` (3,) [m]
    reaches below the sensing hemisphere."""
    pol = math.acos(min(1.0, center[2] / geometry.radius_m))
    if pol + radius_m / geometry.radius_m > math.pi / 2:
        raise ValueError(
            f"{what}: the contact patch (radius {radius_m:.3g} m) around the contact centre"
            " reaches below the sensing hemisphere (z < 0); move it toward the apex"
        )


@dataclass(frozen=True)
class EventParams:
    """Eq. 10 event parameters shared by a generator's emissions: contact speed v0 [m/s],
    object curvature a_c [1/m], indentation rate alpha [1/s]."""

    speed_m_s: float
    curvature_1_m: float
    alpha_1_s: float


def make_emissions(ctx, t_s, pts, kind, params: EventParams, polarity, ids):
    """`EmissionList` of emissions at times ``t_s`` [s] and points ``pts`` (n, 3) [m] with
    one set of event parameters, in the scene's medium (``ctx.config``)."""
    return EmissionList.create(
        to_ns(t_s),
        pts,
        kind,
        polarity=polarity,
        speed_m_s=params.speed_m_s,
        curvature_1_m=params.curvature_1_m,
        alpha_1_s=params.alpha_1_s,
        density_kg_m3=ctx.config.density,
        event_id=ids,
    )


def choose_polarity(drawn, mode):
    """Emission polarities: the random draw (kept so the random stream never changes),
    or all compressions / all rarefactions."""
    if mode == "compression":
        return np.ones_like(drawn)
    if mode == "rarefaction":
        return -np.ones_like(drawn)
    return drawn


def rotate_on_sphere(p0_m, direction, angle_rad):
    """Points (n, 3): p0 (3,) rotated by ``angle_rad`` (n,) about the axis p0 x direction,
    i.e. moved along the great circle through p0 heading along ``direction`` (tangent)."""
    p0 = np.asarray(p0_m, float)
    k = np.cross(p0, np.asarray(direction, float))
    k /= np.linalg.norm(k)
    a = np.asarray(angle_rad, float)[:, None]
    return p0 * np.cos(a) + np.cross(k, p0) * np.sin(a) + k * (k @ p0) * (1 - np.cos(a))
