# SPDX-License-Identifier: Apache-2.0
"""Fingertip geometry: element layout, exact and far-field delays, and their inverse.

Frame (the fingertip frame, ``frame_id`` of every message): origin at the sphere
centre, +z along the PVDF matrix normal toward the fingertip apex, x/y along the
matrix axes. The sensing surface is the upper hemisphere z >= 0 (a planar 2x2
array cannot tell +z from -z).

Channel order, fixed everywhere in the package (messages, protocol, arrays)::

    k : 0        1        2        3
    (xi, eta) = (+1,+1), (+1,-1), (-1,+1), (-1,-1)      -> p_{xi,eta} of the paper

Element k sits at e_k = (xi_k a, eta_k a, 0). A source at s on the sphere
(|s| = R) reaches element k after the straight-path time

    t_k = |s - e_k| / c = sqrt(R^2 + 2 a^2 - 2 a (xi_k s_x + eta_k s_y)) / c.

The paper's Eq. (1) writes p_{xi,eta}(t) = f(t + xi tau_x + eta tau_y), i.e.
t_k = T0 - xi_k tau_x - eta_k tau_y (+ a small "twist" term the paper ignores).
From four arrival times the package defines, exactly,

    tau_x = -(t_0 + t_1 - t_2 - t_3) / 4
    tau_y = -(t_0 - t_1 + t_2 - t_3) / 4
    twist =  (t_0 - t_1 - t_2 + t_3) / 4

and the far-field (a << R) limits are Eq. (2)-(3): tau_x = (a/c) sin(theta) cos(phi),
tau_y = (a/c) sin(theta) sin(phi).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: (xi, eta) of channel k, shape (4, 2); see the module docstring.
CHANNEL_XI_ETA = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=np.int8)
CHANNEL_NAMES = ("p_+1+1", "p_+1-1", "p_-1+1", "p_-1-1")
N_CHANNELS = 4

_XI = CHANNEL_XI_ETA[:, 0].astype(float)
_ETA = CHANNEL_XI_ETA[:, 1].astype(float)


def _positive_finite(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0.0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return value


@dataclass(frozen=True)
class FingertipGeometry:
    """Sphere radius R, element offset a (element centres at (+-a, +-a, 0)), sound speed c.

    Defaults: the paper's water-filled skin, R = 10 mm, a = 1.5 mm, c = 1480 m/s.
    """

    radius_m: float = 10e-3
    element_offset_m: float = 1.5e-3
    sound_speed_m_s: float = 1480.0

    def __post_init__(self) -> None:
        r = _positive_finite("radius_m", self.radius_m)
        a = _positive_finite("element_offset_m", self.element_offset_m)
        _positive_finite("sound_speed_m_s", self.sound_speed_m_s)
        if np.sqrt(2.0) * a >= r:
            raise ValueError(
                f"element_offset_m={a} puts the elements outside the sphere of radius_m={r}"
                " (need sqrt(2) a < R)"
            )

    # ------------------------------------------------------------------ layout
    @property
    def element_positions_m(self) -> np.ndarray:
        """Element centres e_k = (xi_k a, eta_k a, 0), shape (4, 3), metres."""
        a = self.element_offset_m
        return np.stack([_XI * a, _ETA * a, np.zeros(4)], axis=1)

    @property
    def echo_free_duration_s(self) -> float:
        """Shortest time between the direct wave and the first wall echo at any element (s).

        The first echo crosses the body through the centre: path 2R + |s + e_k| against
        |s - e_k| for the direct wave, so at every element the echo lags the direct
        arrival by at least (2R - 2 |e_k|)/c = (2R - 2 sqrt(2) a)/c (10.6 us for the
        default tip; ~2R/c = 13.5 us for a contact above the centre). Analysis windows
        that end within this time after each channel's arrival see only the direct wave.
        """
        return (
            2.0 * self.radius_m - 2.0 * np.sqrt(2.0) * self.element_offset_m
        ) / self.sound_speed_m_s

    @property
    def max_delay_s(self) -> float:
        """Largest |tau_x| or |tau_y| the far-field model allows: a / c (s)."""
        return self.element_offset_m / self.sound_speed_m_s

    # ------------------------------------------------------------------ points
    def surface_point_from_xy(self, x_m, y_m) -> np.ndarray:
        """Point on the upper hemisphere above in-plane (x, y): z = sqrt(R^2 - x^2 - y^2).

        Raises ValueError for points outside the sphere's horizon (x^2 + y^2 > R^2).
        """
        x = np.asarray(x_m, dtype=float)
        y = np.asarray(y_m, dtype=float)
        rho2 = x * x + y * y
        r2 = self.radius_m**2
        if np.any(~np.isfinite(rho2)) or np.any(rho2 > r2 * (1.0 + 1e-12)):
            raise ValueError(
                f"in-plane point(s) outside the sensing surface: need x^2 + y^2 <= R^2"
                f" with R = {self.radius_m} m"
            )
        z = np.sqrt(np.maximum(r2 - rho2, 0.0))
        return np.stack(np.broadcast_arrays(x, y, z), axis=-1)

    def surface_point_from_angles(self, polar_rad, azimuth_rad) -> np.ndarray:
        """s = R (sin th cos ph, sin th sin ph, cos th), shape (..., 3), metres."""
        th = np.asarray(polar_rad, dtype=float)
        ph = np.asarray(azimuth_rad, dtype=float)
        st = np.sin(th)
        return self.radius_m * np.stack(
            np.broadcast_arrays(st * np.cos(ph), st * np.sin(ph), np.cos(th)), axis=-1
        )

    @staticmethod
    def angles_from_points(points_m) -> tuple[np.ndarray, np.ndarray]:
        """(polar, azimuth) in rad of points (..., 3); polar from +z, azimuth from +x."""
        p = np.asarray(points_m, dtype=float)
        rho = np.hypot(p[..., 0], p[..., 1])
        return np.arctan2(rho, p[..., 2]), np.arctan2(p[..., 1], p[..., 0])

    # ------------------------------------------------------------------ forward
    def path_lengths_m(self, points_m) -> np.ndarray:
        """Straight-path distance |s - e_k| from points (..., 3) to the 4 elements: (..., 4)."""
        p = np.asarray(points_m, dtype=float)[..., None, :]
        return np.linalg.norm(p - self.element_positions_m, axis=-1)

    def arrival_times_s(self, points_m) -> np.ndarray:
        """Exact straight-path travel times t_k = |s - e_k| / c, shape (..., 4), seconds."""
        return self.path_lengths_m(points_m) / self.sound_speed_m_s

    @staticmethod
    def delays_from_arrival_times(times_s) -> np.ndarray:
        """(tau_x, tau_y, twist) from arrival times (..., 4): shape (..., 3), seconds."""
        t = np.asarray(times_s, dtype=float)
        tau_x = -(t[..., 0] + t[..., 1] - t[..., 2] - t[..., 3]) / 4.0
        tau_y = -(t[..., 0] - t[..., 1] + t[..., 2] - t[..., 3]) / 4.0
        twist = (t[..., 0] - t[..., 1] - t[..., 2] + t[..., 3]) / 4.0
        return np.stack([tau_x, tau_y, twist], axis=-1)

    def exact_delays_s(self, points_m) -> np.ndarray:
        """(tau_x, tau_y) of the exact geometry for points (..., 3): (..., 2), seconds."""
        return self.delays_from_arrival_times(self.arrival_times_s(points_m))[..., :2]

    def far_field_delays_s(self, points_m) -> np.ndarray:
        """Paper's Eq. (2)-(3): tau = (a/c) (sin th cos ph, sin th sin ph)
        = (a/(cR)) (s_x, s_y)."""
        p = np.asarray(points_m, dtype=float)
        return p[..., :2] * (self.element_offset_m / (self.sound_speed_m_s * self.radius_m))

    def _xy_distances(self, sx, sy) -> np.ndarray:
        """d_k(sx, sy) for points on the sphere (|s| = R): shape (..., 4)."""
        a = self.element_offset_m
        base = self.radius_m**2 + 2.0 * a * a
        arg = base - 2.0 * a * (_XI * sx[..., None] + _ETA * sy[..., None])
        return np.sqrt(arg)

    def arrival_time_derivatives(self, sx_m, sy_m):
        """Exact travel times on the sphere and their first and second derivatives in (s_x, s_y).

        t_k = d_k / c with d_k = sqrt(R^2 + 2 a^2 - 2 a (xi_k s_x + eta_k s_y)), so with
        v_k = (xi_k, eta_k): d t_k/d s = -a v_k / (c d_k) and
        d^2 t_k/d s d s^T = -a^2 v_k v_k^T / (c d_k^3).

        Returns (t (..., 4) s, dt (..., 4, 2) s/m, d2t (..., 4, 2, 2) s/m^2).
        """
        sx = np.asarray(sx_m, dtype=float)
        sy = np.asarray(sy_m, dtype=float)
        sx, sy = np.broadcast_arrays(sx, sy)
        a = self.element_offset_m
        c = self.sound_speed_m_s
        d = self._xy_distances(sx, sy)
        v = CHANNEL_XI_ETA.astype(float)  # (4, 2)
        t = d / c
        dt = (-a / c) * v / d[..., None]
        vv = v[:, :, None] * v[:, None, :]  # (4, 2, 2)
        d2t = (-a * a / c) * vv / (d * d * d)[..., None, None]
        return t, dt, d2t

    def delay_jacobian(self, sx_m, sy_m) -> np.ndarray:
        """d(tau_x, tau_y)/d(s_x, s_y) of the exact model on the sphere, shape (..., 2, 2), s/m.

        With d_k = |s - e_k|: d tau_x/d s_x = d tau_y/d s_y = (a/4c) sum_k 1/d_k,
        d tau_x/d s_y = d tau_y/d s_x = (a/4c) sum_k xi_k eta_k / d_k.
        """
        sx = np.asarray(sx_m, dtype=float)
        sy = np.asarray(sy_m, dtype=float)
        inv_d = 1.0 / self._xy_distances(sx, sy)
        k = self.element_offset_m / (4.0 * self.sound_speed_m_s)
        diag = k * inv_d.sum(axis=-1)
        off = k * (inv_d * (_XI * _ETA)).sum(axis=-1)
        return np.stack([np.stack([diag, off], -1), np.stack([off, diag], -1)], -2)

    # ------------------------------------------------------------------ inverse
    def point_from_delays(
        self, tau_x_s, tau_y_s, exact: bool = True, iterations: int = 8
    ) -> tuple[np.ndarray, np.ndarray]:
        """Contact point on the upper hemisphere from (tau_x, tau_y).

        Far field: (s_x, s_y) = (c R / a) (tau_x, tau_y). With ``exact`` the far-field
        point seeds a vectorized Newton solve of tau(s_x, s_y) = measured on the exact
        model (the 2x2 Jacobian above is well conditioned everywhere on the sphere).

        When noise pushes the implied in-plane radius past R (|sin theta| > 1) the
        point is clamped onto the horizon circle along the measured azimuth, and
        ``clamped`` is True for it. Non-finite delays give NaN points and clamped True;
        callers must reject those before publishing.

        Returns (points (..., 3) in m, clamped (...) bool).
        """
        tx = np.asarray(tau_x_s, dtype=float)
        ty = np.asarray(tau_y_s, dtype=float)
        tx, ty = np.broadcast_arrays(tx, ty)
        r = self.radius_m
        scale = self.sound_speed_m_s * r / self.element_offset_m
        sx = tx * scale
        sy = ty * scale
        limit = r * (1.0 - 1e-9)

        def clamp(sx, sy):
            rho = np.hypot(sx, sy)
            over = rho > limit
            f = np.where(over, limit / np.where(rho > 0, rho, 1.0), 1.0)
            return sx * f, sy * f, over

        sx, sy, clamped = clamp(sx, sy)
        if exact:
            target = np.stack([tx, ty], axis=-1)
            for _ in range(iterations):
                d = self._xy_distances(sx, sy)
                t = d / self.sound_speed_m_s
                pred = self.delays_from_arrival_times(t)[..., :2]
                jac = self.delay_jacobian(sx, sy)
                resid = target - pred
                det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
                dx = (jac[..., 1, 1] * resid[..., 0] - jac[..., 0, 1] * resid[..., 1]) / det
                dy = (jac[..., 0, 0] * resid[..., 1] - jac[..., 1, 0] * resid[..., 0]) / det
                sx, sy, over = clamp(sx + dx, sy + dy)
                # quadratic convergence: stop once every step is below 1e-13 R (~1 fm)
                if not np.any(np.abs(dx) + np.abs(dy) > 1e-13 * r):
                    break
            clamped = over
        bad = ~(np.isfinite(sx) & np.isfinite(sy))
        sz = np.sqrt(np.maximum(r * r - sx * sx - sy * sy, 0.0))
        pts = np.stack([sx, sy, sz], axis=-1)
        pts[bad] = np.nan
        return pts, clamped | bad

    def point_covariance(self, points_m, delay_cov_s2) -> np.ndarray:
        """3x3 covariance (m^2) of a surface point from the 2x2 covariance of (tau_x, tau_y).

        Linear propagation: C_xy = J^-1 C_tau J^-T with J = d tau / d(s_x, s_y), then
        s_z = sqrt(R^2 - s_x^2 - s_y^2) adds the row d s_z/d(s_x, s_y) = -(s_x, s_y)/s_z
        (large near the horizon, where z is poorly determined by in-plane delays).
        """
        p = np.asarray(points_m, dtype=float)
        c_tau = np.asarray(delay_cov_s2, dtype=float)
        jinv = np.linalg.inv(self.delay_jacobian(p[..., 0], p[..., 1]))
        c_xy = jinv @ c_tau @ np.swapaxes(jinv, -1, -2)
        sz = np.maximum(p[..., 2], 1e-6 * self.radius_m)
        g = np.zeros(p.shape[:-1] + (3, 2))
        g[..., 0, 0] = 1.0
        g[..., 1, 1] = 1.0
        g[..., 2, 0] = -p[..., 0] / sz
        g[..., 2, 1] = -p[..., 1] / sz
        return g @ c_xy @ np.swapaxes(g, -1, -2)


#: Medium presets (sound speed in m/s, density in kg/m^3).
MEDIA = {
    "water_skin": {"sound_speed_m_s": 1480.0, "density_kg_m3": 1000.0},
    "silicone": {"sound_speed_m_s": 1000.0, "density_kg_m3": 1030.0},
}

#: Band limit of the PVDF elements and their amplifier (Hz).
PVDF_BAND_HZ = 1e6


def front_end_lowpass(sample_rate_hz: float) -> tuple[float, int]:
    """The front end's Butterworth low-pass (cut-off Hz, order) at an ADC rate f_s:
    (1 MHz, 4), the PVDF band, where that is also a good anti-alias filter; below
    f_s = 3.33 MS/s the ADC's anti-alias filter sets it: (0.3 f_s, 8), which is
    10 log10(1 + (0.5 / 0.3)^16) = 36 dB down at f_s / 2 (a 1 MHz filter before a 2 MS/s ADC
    lets the pulse alias: up to 8x the Cramer-Rao bound at 40 dB)."""
    fc = min(PVDF_BAND_HZ, 0.3 * float(sample_rate_hz))
    return fc, (4 if fc >= PVDF_BAND_HZ else 8)


def resolve_front_end_lowpass(sample_rate_hz: float, lowpass_hz, lowpass_order):
    """(cut-off Hz or None, order) with "auto" resolved: an "auto" cut-off is
    `front_end_lowpass`'s (with its order when the order is "auto" too); an "auto" order
    with a given cut-off (or None) is 4. Other values are returned as given."""
    auto_hz, auto_order = front_end_lowpass(sample_rate_hz)
    hz_auto = isinstance(lowpass_hz, str) and lowpass_hz == "auto"
    order_auto = isinstance(lowpass_order, str) and lowpass_order == "auto"
    hz = auto_hz if hz_auto else lowpass_hz
    order = (auto_order if hz_auto else 4) if order_auto else lowpass_order
    return hz, order


#: Low-pass families of a front end (`front_end_stages`).
LOWPASS_FAMILIES = ("butter", "bessel", "cheby1")


def front_end_stages(highpass_hz=100e3, highpass_order=2, highpass_rc_hz=None,
                     lowpass_hz=1e6, lowpass_order=4, lowpass_family="butter",
                     lowpass_ripple_db=0.5, amplifier_pole_hz=None) -> list:
    """An analog front end as stages (zeros, poles [rad/s], gain), the one definition the
    simulator's chain and the localizer's pulse model share: the high-pass (Butterworth of
    ``highpass_order`` at ``highpass_hz``, or one first-order RC stage per corner of
    ``highpass_rc_hz`` [Hz]), the low-pass (None: none) of ``lowpass_family`` ('butter';
    'bessel', its corner at -3 dB; 'cheby1', ``lowpass_ripple_db`` [dB] of ripple), and
    an optional first-order amplifier pole [Hz]. Unity pass-band gain."""
    from scipy import signal  # lazy: geometry is imported where scipy.signal is not needed

    w = 2 * np.pi
    if highpass_rc_hz is None or len(highpass_rc_hz) == 0:
        stages = [signal.butter(int(highpass_order), w * highpass_hz, btype="highpass",
                                analog=True, output="zpk")]
    else:
        stages = [signal.butter(1, w * f, btype="highpass", analog=True, output="zpk")
                  for f in highpass_rc_hz]
    if lowpass_hz is not None:
        wn, n = w * lowpass_hz, int(lowpass_order)
        if lowpass_family == "bessel":
            stages.append(signal.bessel(n, wn, analog=True, output="zpk", norm="mag"))
        elif lowpass_family == "cheby1":
            stages.append(signal.cheby1(n, lowpass_ripple_db, wn, analog=True, output="zpk"))
        elif lowpass_family == "butter":
            stages.append(signal.butter(n, wn, analog=True, output="zpk"))
        else:
            raise ValueError(f"lowpass_family must be one of {LOWPASS_FAMILIES}, "
                             f"got {lowpass_family!r}")
    if amplifier_pole_hz is not None:
        stages.append(signal.butter(1, w * amplifier_pole_hz, analog=True, output="zpk"))
    return stages
