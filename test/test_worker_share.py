# SPDX-License-Identifier: Apache-2.0
"""Fingertips in one process share one overlap worker (`ae_tactile.pipeline.worker_share`,
as the hand_driver sets up): both resolvers' overlapping windows are answered by it,
correctly and each to its own resolver, and the worker lives as long as its last user."""
import threading

import numpy as np

from ae_eval.overlap_trials import simulate_overlaps
from ae_tactile.pipeline import PacketView, worker_share
from ae_tactile.pipeline.resolver import OverlapResolver
from ae_tactile.sim import SimConfig


def _windows(seed, first_id):
    cfg = SimConfig(reflections=True)
    d = simulate_overlaps(6, cfg, separation_s=np.array([2e-6, 3e-6, 4e-6, 5e-6, 6e-6, 8e-6]),
                          amplitude_ratio=1.0, snr_db=30.0, rng=seed)
    views = [PacketView(d["samples_v"][i], d["sample_rate_hz"], int(d["onset_index"][i]),
                        (1 + i) * 10**9, first_id + i) for i in range(6)]
    return cfg, d, views


def test_two_resolvers_share_one_worker_and_each_gets_its_own_answers():
    worker_share.enable()
    resolvers = []
    try:
        runs = []
        for seed, first_id in ((3, 40), (4, 80)):
            cfg, d, views = _windows(seed, first_id)
            got, done = [], threading.Event()

            def on_records(recs, got=got, done=done):
                got.extend(recs)
                if len(got) >= 12:
                    done.set()

            r = OverlapResolver(cfg.geometry, on_records)
            resolvers.append(r)
            runs.append((r, d, views, got, done, first_id))
        for r, _, views, _, _, _ in runs:
            assert r.ready.wait(300.0)
            r.submit(views, hard=True)  # hard: the worker gives every answer
        for r, d, _, got, done, first_id in runs:
            assert done.wait(300.0), (len(got), dict(r.snapshot_counts()))
            counts = r.snapshot_counts()
            assert counts.get("overlap_worker_answers", 0) >= 6, counts
            assert "overlap_worker_unavailable" not in counts, counts
            solved = 0
            for sid in range(first_id, first_id + 6):
                evs = [e for e in got if e.packet_ids == (sid,)]
                truth = d["points_m"][sid - first_id]
                errs = [np.min(np.linalg.norm(truth - np.array(e.point_m), axis=1)) for e in evs]
                solved += len(evs) == 2 and all(x < 0.1e-3 for x in errs)
            assert solved >= 5, solved
            # each resolver got its own windows' emissions, none of the other's
            assert {e.packet_ids[0] for e in got} <= set(range(first_id, first_id + 6))
        worker = resolvers[0]._proc
        assert worker is not None and resolvers[1]._proc is worker  # one process answered
        resolvers[0].close()
        assert worker.poll() is None  # still the other resolver's
        resolvers[1].close()
        assert worker.wait(10.0) is not None  # the last user ended it
    finally:
        worker_share.enable(False)
        for r in resolvers:
            r.close()
