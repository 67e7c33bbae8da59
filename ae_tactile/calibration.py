# SPDX-License-Identifier: Apache-2.0
"""What the pipeline learns about one device, kept per serial number across restarts.

A fingertip's front end, emission pulse, noise colour and echo are learnt from its own
packets (the learners of the pipeline's stages). `CalibrationStore` keeps their state in
one JSON file per device serial number, ``<directory>/<serial>.json``, so that a restarted
driver starts from what the device taught it last time instead of from the simulator's
nominal model.

The file holds named sections, one per learner, each a JSON mapping the learner writes
(`Learner.calibration_state`) and reads back (`Learner.load_calibration`); the store
never interprets them. A learner that finds a section it cannot use (an older format,
values out of range) says so by raising ValueError: the section is dropped, counted and
learnt again. A damaged file is moved aside (``<serial>.json.bad``), counted and logged:
never a crash, never silently reused.

Writes are atomic (a temporary file in the same directory, then ``os.replace``), so a
driver killed mid-write leaves the previous file.
"""

from __future__ import annotations

import json
import logging
import os
import re
import tempfile
import time
from typing import Protocol

#: format of the file; a file of another version is set aside and learnt again
FORMAT_VERSION = 1
_SAFE = re.compile(r"[^A-Za-z0-9._-]")
_LOG = logging.getLogger("ae_tactile.calibration")


class Learner(Protocol):
    """What the store needs of one learner."""

    def calibration_state(self) -> dict | None:
        """The learnt state as a JSON mapping (None: nothing learnt yet)."""

    def load_calibration(self, state: dict) -> None:
        """Start from a saved state (ValueError: unusable)."""


def default_directory() -> str:
    """``$ROS_HOME/ae_tactile/calibration`` (``~/.ros`` when ROS_HOME is unset)."""
    ros_home = os.environ.get("ROS_HOME") or os.path.join(os.path.expanduser("~"), ".ros")
    return os.path.join(ros_home, "ae_tactile", "calibration")


def file_name(serial: str) -> str:
    """The file of a serial number: characters outside [A-Za-z0-9._-] become '_' (a serial
    is device data: it must not name a path elsewhere)."""
    s = _SAFE.sub("_", str(serial)).strip(".") or "unknown"
    return s[:120] + ".json"


class CalibrationStore:
    """The calibration file of one device.

    Parameters
    ----------
    directory : str
        Where the files live (created on the first save).
    serial : str
        The device's serial number (its STATUS); names the file.
    reset : bool
        Ignore what the file holds (start learning from scratch; the next save overwrites
        it).

    Returns
    -------
    CalibrationStore
    """

    def __init__(self, directory: str, serial: str, reset: bool = False):
        self.directory = str(directory)
        self.serial = str(serial)
        self.path = os.path.join(self.directory, file_name(serial))
        self.reset = bool(reset)
        #: what happened: files_loaded, sections_loaded, sections_rejected, files_damaged,
        #: saves, save_errors
        self.counts = dict.fromkeys(("files_loaded", "sections_loaded", "sections_rejected",
                                     "files_damaged", "saves", "save_errors"), 0)
        #: the last problem, for diagnostics ('' if none)
        self.last_error = ""
        self.loaded_sections: list[str] = []

    # ------------------------------------------------------------------ reading
    def read(self) -> dict:
        """The sections of the file ({} when there is none, on reset, or when it is
        damaged: then it is moved aside to ``<file>.bad`` and counted).

        Returns
        -------
        dict
            section name -> state mapping.
        """
        if self.reset or not os.path.exists(self.path):
            return {}
        try:
            with open(self.path, encoding="utf-8") as fh:
                doc = json.load(fh)
            if not isinstance(doc, dict) or doc.get("format") != FORMAT_VERSION:
                raise ValueError(f"not a format-{FORMAT_VERSION} calibration file")
            sections = doc.get("sections")
            if not isinstance(sections, dict) or not all(
                isinstance(v, dict) for v in sections.values()
            ):
                raise ValueError("its sections are not mappings")
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            self._set_aside(exc)
            return {}
        self.counts["files_loaded"] += 1
        return sections

    def _set_aside(self, exc: Exception) -> None:
        self.counts["files_damaged"] += 1
        self.last_error = f"{self.path}: {exc}"
        try:
            os.replace(self.path, self.path + ".bad")
            where = f"moved to {self.path}.bad"
        except OSError as err:
            where = f"could not be moved aside ({err})"
        _LOG.warning("calibration file %s unusable (%s): %s; learning again", self.path,
                     exc, where)

    def load_into(self, learners: dict) -> list[str]:
        """Give each learner its saved section.

        Parameters
        ----------
        learners : dict
            section name -> `Learner`.

        Returns
        -------
        list of str
            The sections loaded (a learner that raised ValueError is counted in
            ``sections_rejected``, logged, and keeps learning from scratch).
        """
        sections = self.read()
        done = []
        for name, learner in learners.items():
            state = sections.get(name)
            if state is None:
                continue
            try:
                learner.load_calibration(state)
            except (ValueError, TypeError, KeyError) as exc:
                self.counts["sections_rejected"] += 1
                self.last_error = f"section {name!r}: {exc}"
                _LOG.warning("calibration of %s: section %r not used (%s); learning it again",
                             self.serial, name, exc)
                continue
            done.append(name)
        self.counts["sections_loaded"] += len(done)
        self.loaded_sections = done
        return done

    # ------------------------------------------------------------------ writing
    def save(self, learners: dict) -> bool:
        """Write every learner's state (those with nothing learnt are left out), atomically.

        Parameters
        ----------
        learners : dict
            section name -> `Learner`.

        Returns
        -------
        bool
            True when written (False: nothing to write, or an error, counted in
            ``save_errors`` and logged).
        """
        sections = {}
        for name, learner in learners.items():
            state = learner.calibration_state()
            if state is not None:
                sections[name] = state
        if not sections:
            return False
        doc = dict(format=FORMAT_VERSION, serial=self.serial, saved_unix_s=time.time(),
                   sections=sections)
        try:
            os.makedirs(self.directory, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".calibration-", dir=self.directory)
            try:
                with os.fdopen(fd, "w", encoding="utf-8") as fh:
                    json.dump(doc, fh, indent=1, allow_nan=False)
                os.replace(tmp, self.path)
            except BaseException:
                os.unlink(tmp)
                raise
        except (OSError, ValueError, TypeError) as exc:
            self.counts["save_errors"] += 1
            self.last_error = f"save {self.path}: {exc}"
            _LOG.warning("calibration of %s not saved: %s", self.serial, exc)
            return False
        self.counts["saves"] += 1
        self.reset = False  # what is on disk is ours now
        return True

    def delete(self) -> bool:
        """Remove the device's file (a reset that outlives the driver). True if removed.

        Returns
        -------
        bool
        """
        try:
            os.remove(self.path)
            return True
        except FileNotFoundError:
            return False
