# SPDX-License-Identifier: Apache-2.0
"""Offline replay of recorded raw packets: rosbag2 (sqlite3 or MCAP) -> events, without ROS.

Like velodyne's raw-packet bags, a bag of `PacketArray` can be re-interpreted later with
other parameters: this reads it with the pure-Python `rosbags` library, re-runs the
localization core (any estimator) and the slip detector, and writes the events to a new
rosbag2 (topics `contacts` and `slip`, ContactEvent; same namespace as the packets) or to
a CSV file.

    python -m ae_tactile.bagtools IN_BAG OUT(.csv | bag dir) [--method ml] [--storage mcap]

Exit codes of the command: 0 the bag was read completely; 3 the bag is damaged or had
undecodable messages: the events of what was readable were written, the summary says
what was lost; 2 nothing to replay (input missing or unreadable, bad arguments) or the
output could not be written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ae_tactile.localization import available_methods
from ae_tactile.slip import SlipConfig

from .export import write_bag, write_csv, write_png
from .replay import replay


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="ae-tactile-replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", help="input rosbag2 directory (or .mcap / .db3 file) with PacketArray")
    ap.add_argument("out", help="output: a .csv file, or a new rosbag2 directory")
    ap.add_argument(
        "--method", default="ml", choices=available_methods(), help="localization estimator"
    )
    ap.add_argument("--topic", default=None, help="PacketArray topic (default: all)")
    ap.add_argument(
        "--storage", default="sqlite3", choices=("sqlite3", "mcap"), help="output bag storage"
    )
    ap.add_argument(
        "--sliding-speed", type=float, default=0.0, help="known sliding speed (m/s) for textures"
    )
    ap.add_argument(
        "--png", default="", help="also write a PNG summary of the replay (needs matplotlib)"
    )
    return ap


def main(argv=None) -> int:
    """The ``ae-tactile-replay`` command.

    Parameters
    ----------
    argv : list of str or None
        Its arguments (None: sys.argv[1:]).

    Returns
    -------
    int
        Exit code: 0 complete, 3 the bag was damaged, 2 nothing replayed or written.
    """
    args = _parser().parse_args(argv)
    cfg = SlipConfig(sliding_speed_m_s=args.sliding_speed or None)
    try:
        res = replay(args.bag, method=args.method, packet_topic=args.topic, slip_config=cfg)
    except (FileNotFoundError, ValueError) as exc:
        print(f"ae-tactile-replay: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - a summary, no traceback
        print(
            f"ae-tactile-replay: cannot replay {args.bag}: {type(exc).__name__}: {exc}",
            file=sys.stderr,
        )
        return 2
    if res.damaged and not res.packets and not res.contacts:
        print(
            f"ae-tactile-replay: nothing readable in {args.bag}\n{res.summary()}", file=sys.stderr
        )
        return 2
    try:
        if args.out.endswith(".csv"):
            n = write_csv(res, args.out)
        else:
            n = write_bag(res, args.out, args.storage)
    except Exception as exc:  # noqa: BLE001
        print(
            f"ae-tactile-replay: cannot write {args.out}: {type(exc).__name__}: {exc}",
            file=sys.stderr,
        )
        return 2
    print(f"{res.summary()}\n{n} events written to {args.out}")
    if args.png:
        write_png(res, args.png, title=f"replay of {Path(args.bag).name}")
    return 3 if res.damaged else 0
