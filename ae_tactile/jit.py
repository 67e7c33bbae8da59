# SPDX-License-Identifier: Apache-2.0
"""The optional compiler, in one place: ``njit`` and ``NUMBA_AVAILABLE``.

numba compiles the hot kernels (simulator, `ml` localization, the link's per-packet
front end); every one of them has a numpy twin that runs where numba is absent, and the
tests check that the two agree. ``AE_TACTILE_NO_NUMBA=1`` in the environment forces the
numpy paths (as on a machine without numba). Without numba, ``njit`` returns the plain
Python function, so a kernel stays importable (and callable, slowly) either way.
"""

from __future__ import annotations

import os

try:  # pragma: no cover - import guard
    if os.environ.get("AE_TACTILE_NO_NUMBA", "").strip() not in ("", "0"):
        raise ImportError("disabled by AE_TACTILE_NO_NUMBA")
    from numba import njit

    NUMBA_AVAILABLE = True
except ImportError:  # pragma: no cover - exercised only without numba
    NUMBA_AVAILABLE = False

    def njit(*args, **kwargs):
        """Stand-in decorator: the function itself (numba absent or disabled)."""

        def wrap(fn):
            return fn

        return args[0] if len(args) == 1 and callable(args[0]) and not kwargs else wrap


__all__ = ["NUMBA_AVAILABLE", "njit"]
