# SPDX-License-Identifier: Apache-2.0
"""Recorded AE data in: read recordings, find hits, locate events, replay a fingertip.

Data flow: `readers` (WAV, Vallen pridb/tradb, CSV, NPY/NPZ -> `Recording` in volts) ->
`hits` (hit definition in AE terms -> `Hit` per channel) -> `locate` (planar
time-difference location on a plate, LUCY) and `fingertip` (4-channel windows through the
live device's `ContactPipeline`) -> `api` (`detect`, `write_detections`) -> `cli`
(``ae-tactile-detect``). docs/recordings.md is the reference.
"""

from .api import FINGERTIP_DDT_US, Detection, detect, tables, write_detections
from .fingertip import FingertipReplay, replay_fingertip
from .hits import Hit, HitDefinition, db_ae_to_v, find_hits, noise_floor_v, v_to_db_ae
from .locate import PlanarEvent, locate_events, locate_planar, lucy_m, read_vallen_setup
from .readers import (
    Recording,
    RecordingError,
    VallenHit,
    read_recording,
    read_vallen_hits,
)

__all__ = [
    "Detection", "detect", "tables", "write_detections", "FINGERTIP_DDT_US",
    "FingertipReplay", "replay_fingertip",
    "Hit", "HitDefinition", "db_ae_to_v", "v_to_db_ae", "find_hits", "noise_floor_v",
    "PlanarEvent", "locate_events", "locate_planar", "lucy_m", "read_vallen_setup",
    "Recording", "RecordingError", "VallenHit", "read_recording", "read_vallen_hits",
]
