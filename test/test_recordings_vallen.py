# SPDX-License-Identifier: Apache-2.0
"""Vallen pridb/tradb recordings: Vallen's own steel-plate example (one pencil-lead break,
4 sensors, 5 MS/s; test/data/vallen_steel_plate) against the acquisition's hardware hit
times, hit features and LUCY location, and a plate recording the test writes with
vallenae's writer against its known source."""

import subprocess
from pathlib import Path

import numpy as np
import pytest

vae = pytest.importorskip("vallenae", reason="vallenae (optional, tools/requirements.txt) "
                                             "reads Vallen pridb/tradb files")

from ae_tactile.recordings import (  # noqa: E402
    RecordingError,
    detect,
    locate_planar,
    lucy_m,
    read_recording,
    read_vallen_hits,
    read_vallen_setup,
)
from ae_tactile.recordings.cli import main as cli_main  # noqa: E402

DATA = Path(__file__).resolve().parent / "data" / "vallen_steel_plate"
PRIDB = DATA / "sample.pridb"
FS_PLATE = 5e6


@pytest.fixture(scope="module")
def plate():
    pos, v = read_vallen_setup(DATA / "sample.vaex")
    vallen = read_vallen_hits(PRIDB)
    det = detect(PRIDB)  # the .vaex beside it: positions and speed
    return {"pos": pos, "v": v, "vallen": vallen, "det": det}


def test_the_setup_file_gives_positions_and_speed(plate):
    assert plate["pos"] == {1: (0.6, 0.6), 2: (0.15, 0.6), 3: (0.15, 0.15), 4: (0.6, 0.15)}
    assert plate["v"] == 5000.0
    assert [h.channel for h in plate["vallen"]] == [3, 2, 4, 1]


def test_steel_plate_onsets_within_a_few_samples_of_vallens_hit_times(plate):
    """One hit per channel (each a 20 ms ringing); the first threshold crossing within one
    sample of Vallen's hardware arrival time, the AIC onset a few samples before it."""
    hits = {h.channel: h for h in plate["det"].hits}
    assert len(plate["det"].hits) == 4 and set(hits) == {1, 2, 3, 4}
    for v in plate["vallen"]:
        h = hits[v.channel]
        assert abs(h.crossing_time_s - v.time_s) * FS_PLATE <= 1.0 + 1e-6
        d = (h.onset_time_s - v.time_s) * FS_PLATE
        assert -10.0 <= d <= 0.5, (v.channel, d)  # samples: 2 us at most before the crossing


def test_steel_plate_hit_features_match_vallens(plate):
    hits = {h.channel: h for h in plate["det"].hits}
    for v in plate["vallen"]:
        h = hits[v.channel]
        assert h.peak_v == pytest.approx(v.amplitude_v, rel=0.01)
        assert h.duration_s == pytest.approx(v.duration_s, rel=0.002)
        assert h.rise_time_s == pytest.approx(v.rise_time_s, abs=0.5e-6)
        assert h.energy_eu == pytest.approx(v.energy_eu, rel=0.01)
        assert h.counts == pytest.approx(v.counts, rel=0.03)


def _lucy_grid_min(times, xy, v, step=1e-3):
    """Brute-force LUCY minimum over the plate (an independent check of the optimiser)."""
    order = np.argsort(times)
    t, s = np.asarray(times)[order], np.asarray(xy)[order]
    g = np.arange(0.0, 0.8, step)
    px, py = np.meshgrid(g, g)
    d = np.hypot(px[..., None] - s[:, 0], py[..., None] - s[:, 1])
    r = (d[..., 1:] - d[..., :1]) - v * (t[1:] - t[0])
    k = np.unravel_index(np.argmin((r * r).sum(-1)), px.shape)
    return px[k], py[k]


def test_steel_plate_location_within_a_few_mm_of_vallens(plate):
    """Vallen's location: the LUCY minimum of the pridb's hardware arrival times; ours
    from our own onsets. Both by the same LUCY minimisation; the reference is checked
    against a brute-force grid."""
    pos, v = plate["pos"], plate["v"]
    t_ref = [h.time_s for h in plate["vallen"]]
    xy_ref = [pos[h.channel] for h in plate["vallen"]]
    rx, ry, rl = locate_planar(t_ref, xy_ref, v)
    gx, gy = _lucy_grid_min(t_ref, xy_ref, v)
    assert np.hypot(rx - gx, ry - gy) < 1e-3
    assert lucy_m((rx, ry), sorted(t_ref), [xy_ref[i] for i in np.argsort(t_ref)], v) == \
        pytest.approx(rl)
    (ev,) = plate["det"].events
    assert ev.reason == "" and len(ev.channels) == 4
    err = np.hypot(ev.x_m - rx, ev.y_m - ry)
    assert err < 5e-3, err  # [m]
    assert ev.lucy_m < 2e-3


def test_steel_plate_from_the_command_line(capsys, tmp_path):
    out = tmp_path / "plate.json"
    assert cli_main([str(PRIDB), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "4 transient records at 5 MS/s; 4 hit(s)" in text and "located events" in text
    assert "sample.vaex" in text
    assert '"lucy_m"' in out.read_text()


def test_the_installed_command_runs(tmp_path):
    from conftest import installed_executable

    exe = installed_executable("ae_tactile_detect")
    run = subprocess.run([exe, str(PRIDB)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "located events" in run.stdout


# ------------------------------------------------------------------ a written recording
SENSORS = np.array([[0.0, 0.0], [0.5, 0.0], [0.5, 0.5], [0.0, 0.5]])
V_PLATE = 3000.0
FS = 2_000_000
PRE = 200  # pre-trigger samples
SOURCES = [((0.12, 0.31), 1.000_123_4), ((0.40, 0.07), 1.250_000_7)]  # (x, y) [m], time [s]


def _burst(n, onset, amp, rng):
    t = (np.arange(n) - onset) / FS
    tt = np.clip(t, 0, None)
    x = amp * (1 - np.exp(-tt / 2e-6)) * np.exp(-tt / 200e-6) * np.sin(2 * np.pi * 150e3 * tt)
    return np.where(t >= 0, x, 0.0) + rng.normal(0, 5e-6, n)


def _write_plate(d: Path):
    """A pridb/tradb pair as an AMSY system writes it: one transient record per hit with
    200 pre-trigger samples, and the hits with their arrival times."""
    rng = np.random.default_rng(4)
    arrivals = []
    with vae.io.TraDatabase(str(d / "plate.tradb"), mode="rwc") as tra, \
            vae.io.PriDatabase(str(d / "plate.pridb"), mode="rwc") as pri:
        tra.connection().execute("INSERT INTO tr_params (ID, SetupID, Chan, ADC_µV, TR_mV) "
                                 "VALUES (1, 1, 1, 1, 0.001)")  # 1 uV per code
        pri.connection().execute("INSERT INTO ae_params (ID, SetupID, Chan, ADC_µV, ADC_TE, "
                                 "ADC_SS) VALUES (1, 1, 1, 1, 1, 1)")
        trai = 0
        for (sx, sy), t0 in SOURCES:
            t_arr = t0 + np.hypot(SENSORS[:, 0] - sx, SENSORS[:, 1] - sy) / V_PLATE
            for ch in np.argsort(t_arr):
                trai += 1
                first = int(np.floor(t_arr[ch] * FS)) - PRE  # the record's first sample
                y = _burst(4000, t_arr[ch] * FS - first, 10e-3, rng)
                tra.write(vae.io.TraRecord(time=(first + PRE) / FS, channel=int(ch) + 1,
                                           param_id=1, pretrigger=PRE, threshold=1e-4,
                                           samplerate=FS, samples=y.size,
                                           data=y.astype(np.float32), trai=trai))
                pri.write_hit(vae.io.HitRecord(time=float(t_arr[ch]), channel=int(ch) + 1,
                                               param_id=1, amplitude=10e-3, duration=1e-3,
                                               energy=1.0, rms=5e-6, threshold=1e-4,
                                               counts=100, trai=trai))
                arrivals.append((int(ch) + 1, float(t_arr[ch])))
    return arrivals


def test_a_written_plate_recording_is_read_detected_and_located(tmp_path):
    arrivals = _write_plate(tmp_path)
    hw = read_vallen_hits(tmp_path / "plate.tradb")
    written = sorted(arrivals, key=lambda a: a[1])
    assert [h.channel for h in hw] == [c for c, _ in written]
    assert np.allclose([h.time_s for h in hw], [t for _, t in written], rtol=0,
                       atol=1.01e-7)  # the pridb's time base: 100 ns
    recs = read_recording(tmp_path / "plate.pridb")
    assert len(recs) == 8 and all(r.pretrigger_samples == PRE for r in recs)
    assert recs[0].threshold_v == pytest.approx(1e-4) and recs[0].sample_rate_hz == FS
    det = detect(tmp_path / "plate.pridb", sensor_xy=SENSORS, velocity_m_s=V_PLATE)
    assert len(det.hits) == 8 and not det.warnings
    truth = dict(((c, round(t, 3)), t) for c, t in arrivals)
    for h in det.hits:
        t = truth[(h.channel, round(h.onset_time_s, 3))]
        assert abs(h.onset_time_s - t) * FS <= 3.0  # samples
    assert len(det.events) == 2
    for ev, ((sx, sy), _) in zip(det.events, SOURCES):
        assert np.hypot(ev.x_m - sx, ev.y_m - sy) < 2e-3, ev
    text = ";".join(f"{x},{y}" for x, y in SENSORS)
    assert cli_main([str(tmp_path / "plate.tradb"), "--sensor-xy", text,
                     "--velocity-m-s", "3000"]) == 0


def test_bad_vallen_files(tmp_path):
    _write_plate(tmp_path)
    (tmp_path / "plate.tradb").rename(tmp_path / "other.tradb")
    with pytest.raises(RecordingError, match="plate.pridb: no .tradb file beside it"):
        read_recording(tmp_path / "plate.pridb")
    (tmp_path / "other.pridb").write_bytes(b"SQLite format 3\x00" + b"\x00" * 200)
    with pytest.raises(RecordingError, match="other.pridb: not a readable Vallen pridb"):
        read_vallen_hits(tmp_path / "other.pridb")
    with pytest.raises(ValueError, match="sensor positions given without velocity_m_s"):
        detect(tmp_path / "other.tradb", sensor_xy="0,0;1,0;0,1")
    with pytest.raises(ValueError, match="4 channels .* but only 3 sensor positions"):
        detect(tmp_path / "other.tradb", sensor_xy="0,0;1,0;0,1", velocity_m_s=3000.0)
