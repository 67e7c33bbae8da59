# SPDX-License-Identifier: Apache-2.0
"""Ground truth of simulated scenes read back for scoring (evaluation only: the product
never needs it).
"""
from __future__ import annotations

import numpy as np

from ae_tactile.sim.generator_tools import rotate_on_sphere


def stylus_track(truth: dict, radius_m: float, t_ns):
    """Centre and velocity of a stylus scene's contact (`ae_tactile.sim.generators.stylus`)
    at given times, from the track its truth records.

    Parameters
    ----------
    truth : dict
        The stylus scene's ``scene_truth()`` (start/end times, start point, direction,
        slide speed).
    radius_m : float
        Fingertip sphere radius [m].
    t_ns : array_like
        Times (n,) [ns]; clipped to the slide.

    Returns
    -------
    centre : ndarray
        (n, 3) contact centre on the sphere [m].
    velocity : ndarray
        (n, 3) its velocity [m/s] (finite difference over 1 us).
    """
    t = (np.atleast_1d(np.asarray(t_ns, float)) - truth["start_time_ns"]) * 1e-9
    t = np.clip(t, 0.0, (truth["end_time_ns"] - truth["start_time_ns"]) * 1e-9)
    p0, d, v = (
        np.asarray(truth["start_point_m"]),
        np.asarray(truth["direction"]),
        truth["slide_speed_m_s"],
    )
    c = rotate_on_sphere(p0, d, v * t / radius_m)
    c2 = rotate_on_sphere(p0, d, v * (t + 1e-6) / radius_m)
    return c, (c2 - c) / 1e-6
