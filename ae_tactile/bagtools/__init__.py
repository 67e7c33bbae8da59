# SPDX-License-Identifier: Apache-2.0
"""Offline replay of recorded raw packets: rosbag2 (sqlite3 or MCAP) -> events, without ROS.

A bag of `PacketArray` is re-interpreted with other parameters: read with the
pure-Python `rosbags` library, re-localized (any estimator), run through the slip
detector, and written as a new rosbag2 or a CSV file (``ae-tactile-replay``,
``python -m ae_tactile.bagtools``; `cli` says how).

Damaged bags: what is readable is recovered (`recovery`); messages of other types are
skipped and counted, undecodable ones counted, bad packets rejected one by one with
their reason. The replay ends with a summary (`ReplayResult.summary`).

Modules, along the data flow: `reader` (message types, `read_bag`, `ReplayResult`),
`recovery` (sqlite3 and MCAP record by record), `replay` (packets -> contact and slip
events), `export` (CSV, rosbag2, PNG), `cli` (the command).
"""

from .cli import main
from .export import CSV_FIELDS, write_bag, write_csv, write_png
from .reader import MSG_NAMES, WANTED, ReplayResult, msg_dir, read_bag, typestore
from .replay import DETOUCH, TOUCH, check_packet, replay

__all__ = [
    "CSV_FIELDS",
    "DETOUCH",
    "MSG_NAMES",
    "TOUCH",
    "WANTED",
    "ReplayResult",
    "check_packet",
    "main",
    "msg_dir",
    "read_bag",
    "replay",
    "typestore",
    "write_bag",
    "write_csv",
    "write_png",
]
