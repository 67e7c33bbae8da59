# SPDX-License-Identifier: Apache-2.0
"""Compile every numba kernel into numba's on-disk cache: ``python -m ae_tactile.compile_kernels``.

numba compiles a kernel the first time a process calls it and keeps the machine code in
``__pycache__`` next to the source (keyed by the source file's modification time and the
CPU). On a new machine that first compilation of the localization, link and simulator kernels
takes about a minute of CPU; loading them from the cache afterwards takes ~1-2 s.
`tools/setup.sh` runs this once after a build (and again when a kernel source changes), so
that neither the driver's warm-up nor a test pays the compilation. Without numba it does
nothing (the numpy paths need no compilation).
"""

from __future__ import annotations

import os
import sys
import time


def compile_kernels() -> dict:
    """Compile (or load) the simulator and localization kernels; seconds per part."""
    # lazy: nothing below is imported when numba is absent (nothing to compile)
    from ae_tactile.localization.fast import NUMBA_AVAILABLE  # lazy: see above
    from ae_tactile.sim.kernels import HAVE_NUMBA  # lazy: see above

    out = {"numba": bool(NUMBA_AVAILABLE or HAVE_NUMBA)}
    if not out["numba"]:
        return out
    from ae_tactile.link import warm_up as warm_link  # lazy: only with numba
    from ae_tactile.pipeline import PacketLocalizer  # lazy: only with numba
    from ae_tactile.sim.kernels import warm_up as warm_sim  # lazy: only with numba

    t0 = time.perf_counter()
    warm_sim()
    t1 = time.perf_counter()
    for fs in (10e6, 2e6):  # the built-in parameter files' sample rates
        PacketLocalizer("ml", reject_interference=True).warm_up(fs, 400)
    warm_link()
    t2 = time.perf_counter()
    out.update(simulator_s=round(t1 - t0, 2), localization_s=round(t2 - t1, 2))
    return out


def main(argv=None) -> int:
    res = compile_kernels()
    if not res["numba"]:
        print("numba not available: the numpy paths run, nothing to compile")
        return 0
    import ae_tactile  # lazy: the path printed only

    print(
        f"numba kernels of {os.path.dirname(ae_tactile.__file__)} ready: "
        f"simulator {res['simulator_s']:.1f} s, localization {res['localization_s']:.1f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
