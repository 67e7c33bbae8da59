# SPDX-License-Identifier: Apache-2.0
"""What the pipeline learnt about a device, loaded when the device is known and saved as
it goes (`ae_tactile.calibration.CalibrationStore`, one file per serial number and body:
what was learnt on one body -- its radius, element offset and sound speed -- is never
applied to another, e.g. a fingertip refilled with another medium).

The driver's reader thread calls `DeviceCalibration.on_device` with the device's serial
number before each batch (nothing happens while it is unchanged) and `save_due` when it
is idle; `close` saves once more at shutdown. All three run where the learners are used
(the reader thread, or after it stopped), so no lock is needed.
"""

from __future__ import annotations

import logging
import time

from ae_tactile.calibration import CalibrationStore, default_directory

_LOG = logging.getLogger("ae_tactile.calibration")


class DeviceCalibration:
    """The calibration of the device a pipeline reads.

    Parameters
    ----------
    learners : callable
        Returns the pipeline's learners (section name -> learner with
        ``calibration_state`` / ``load_calibration``), e.g.
        ``ContactPipeline.calibration_learners``.
    directory : str
        Where the files live ('' : `default_directory`).
    reset : bool
        Start the first device from scratch (its file is overwritten by the next save).
    save_period_s : float
        Save at most this often while running [s] (and at `close`).
    clock : callable
        Monotonic time [s] (tests pass their own).
    body : callable, optional
        Returns the fingertip's `FingertipGeometry` now: its file is that of the serial
        number and this body (another body, another file).

    Returns
    -------
    DeviceCalibration
    """

    def __init__(self, learners, directory: str = "", reset: bool = False,
                 save_period_s: float = 60.0, clock=time.monotonic, body=None):
        self._learners = learners
        self._body = body
        self.directory = directory or default_directory()
        self._reset = bool(reset)
        self.save_period_s = float(save_period_s)
        self._clock = clock
        self.store: CalibrationStore | None = None
        self._last_save = clock()

    def on_device(self, serial: str | None) -> None:
        """The device being read is ``serial`` (None: not known yet). A new serial, or the
        same on another body (`key`), saves the previous calibration, resets the learners
        and loads the new one's.

        Parameters
        ----------
        serial : str or None

        Returns
        -------
        None
        """
        if not serial:
            return
        serial = self.key(serial)
        if self.store is not None and self.store.serial == serial:
            return
        learners = self._learners()
        if self.store is not None:
            self.store.save(learners)
            for learner in learners.values():
                reset = getattr(learner, "reset", None)
                if reset is not None:
                    reset()
            _LOG.warning("device changed from %s to %s: its own calibration from now on",
                         self.store.serial, serial)
        store = CalibrationStore(self.directory, serial, reset=self._reset)
        self._reset = False  # a reset applies to the device the driver started with
        loaded = store.load_into(learners)
        # in use once loaded: `status` (another thread's diagnostics) never shows the new
        # file with nothing loaded yet
        self.store = store
        if loaded:
            _LOG.info("calibration of %s loaded from %s: %s", serial, store.path,
                      ", ".join(loaded))
        else:
            _LOG.info("no calibration of %s in %s yet: learning it from its packets",
                      serial, store.path)
        self._last_save = self._clock()

    def key(self, serial: str) -> str:
        """The file's name for ``serial`` on the current body: ``<serial>_R<radius mm>_a<element
        offset mm>_c<sound speed m/s>`` (the serial alone without ``body``)."""
        if self._body is None:
            return serial
        g = self._body()
        return (f"{serial}_R{g.radius_m * 1e3:g}mm_a{g.element_offset_m * 1e3:g}mm"
                f"_c{g.sound_speed_m_s:g}")

    def save_due(self) -> bool:
        """Save when ``save_period_s`` has passed since the last save. True if written.

        Returns
        -------
        bool
        """
        if self.store is None or self._clock() - self._last_save < self.save_period_s:
            return False
        self._last_save = self._clock()
        return self.store.save(self._learners())

    def close(self) -> bool:
        """Save now (shutdown). True if written.

        Returns
        -------
        bool
        """
        if self.store is None:
            return False
        return self.store.save(self._learners())

    def status(self) -> dict:
        """For diagnostics: the file, the sections loaded, the store's counts, the last
        problem, and each learner's state in words where it says it (``calibration_<section>``,
        e.g. ``calibration_overlap_pulse``: learnt, loaded and being checked, or the
        nominal pulse while learning).

        Returns
        -------
        dict
        """
        out = {}
        if self.store is None:
            out["calibration_file"] = "(device not known yet)"
        else:
            s = self.store
            out["calibration_file"] = s.path
            out["calibration_loaded"] = ",".join(s.loaded_sections) or "(none)"
            out.update({f"calibration_{k}": v for k, v in s.counts.items()})
            if s.last_error:
                out["calibration_last_error"] = s.last_error
        for name, learner in self._learners().items():
            status = getattr(learner, "status", None)
            if callable(status):
                out[f"calibration_{name}"] = status()
        return out
