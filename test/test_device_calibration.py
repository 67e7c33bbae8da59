# SPDX-License-Identifier: Apache-2.0
"""A restarted driver starts from what its device taught the pipeline: the learners'
state saved per serial number and loaded when the device is known again. On a textbook
front end (two RC high-pass stages and a 6th-order Bessel anti-alias filter) a fresh
pipeline takes apex touches for interference until it has learnt the device; loaded from
the device's file, it keeps them from the first packet, and still rejects bursts."""

import numpy as np
import pytest

from ae_eval.zoo import ZOO
from ae_tactile.pipeline import ContactPipeline, PacketLocalizer
from ae_tactile.pipeline.device_calibration import DeviceCalibration
from ae_tactile.records import PacketView
from ae_tactile.sim import render_triggered
from ae_tactile.sim.interference import render_interference
from ae_tactile.sim.scene import reference_noise_rms


def _cap(cfg, n, g, max_deg, min_deg=0.0):
    cos_t = g.uniform(np.cos(np.radians(max_deg)), np.cos(np.radians(min_deg)), n)
    return cfg.geometry.surface_point_from_angles(np.arccos(cos_t), g.uniform(0, 2 * np.pi, n))


def _feed(pipe, pk, fs, t0_ns, id0):
    """The packets at random times (a hand's timing, not a crystal's: the burst-train
    screen stays out of it), in batches of 10 with idle work between; the ids kept."""
    kept = []
    n = len(pk.samples_v)
    t_ns = t0_ns + np.sort(np.random.default_rng(id0).integers(0, n * 37_000_000, n))
    views = [PacketView(pk.samples_v[i], fs, int(pk.onset_index[i]), int(t_ns[i]), id0 + i)
             for i in range(n)]
    for k in range(0, len(views), 10):
        pipe.process(views[k : k + 10], kept.extend)
        pipe.run_idle_work()
    return {e.packet_ids[0] for e in kept}


@pytest.fixture(scope="module")
def device():
    dev = ZOO["rc2_bessel6"]
    cfg = dev.config("water_skin", 10e6)
    g = np.random.default_rng(11)
    n = 300
    touches = render_triggered(_cap(cfg, n, g, 60.0), cfg, snr_db=g.uniform(20, 40, n),
                               polarity=g.choice([-1, 1], n), rng=g)
    noise = reference_noise_rms(cfg, 30.0)
    apex = render_triggered(_cap(cfg, 40, g, 3.0), cfg, noise_rms_v=noise, rng=g)
    bursts = render_interference(40, cfg, kind="mixed", coupling="adc", noise_rms_v=noise, rng=g)
    return cfg, touches, apex, bursts


def _pipeline(cfg):
    return ContactPipeline(PacketLocalizer("ml", geometry=cfg.geometry), None)


def test_a_restarted_pipeline_starts_from_the_devices_saved_calibration(tmp_path, device):
    cfg, touches, apex, bursts = device
    fs = cfg.sample_rate_hz
    first = _pipeline(cfg)
    cal = DeviceCalibration(first.calibration_learners, str(tmp_path))
    cal.on_device("AE-0007")
    _feed(first, touches, fs, 0, 0)  # the device in use: the pipeline learns it
    assert cal.close()
    assert cal.status()["calibration_saves"] == 1

    cold = _pipeline(cfg)  # a restart without the file: apex touches taken for bursts
    cold_kept = _feed(cold, apex, fs, 0, 0)
    warm = _pipeline(cfg)
    again = DeviceCalibration(warm.calibration_learners, str(tmp_path))
    again.on_device("AE-0007")
    assert again.status()["calibration_loaded"] != "(none)"
    warm_kept = _feed(warm, apex, fs, 0, 0)
    burst_kept = _feed(warm, bursts, fs, 10**10, 1000)
    assert len(warm_kept) >= 39  # >= 97.5 % of 40 apex touches from the first packet
    assert len(cold_kept) < len(warm_kept)
    assert len(burst_kept) == 0


def test_another_device_or_a_reset_does_not_get_this_devices_calibration(tmp_path, device):
    cfg, touches, apex, _ = device
    fs = cfg.sample_rate_hz
    first = _pipeline(cfg)
    cal = DeviceCalibration(first.calibration_learners, str(tmp_path))
    cal.on_device("AE-0007")
    _feed(first, touches, fs, 0, 0)
    cal.close()
    for serial, reset in (("AE-0008", False), ("AE-0007", True)):
        p = _pipeline(cfg)
        c = DeviceCalibration(p.calibration_learners, str(tmp_path), reset=reset)
        c.on_device(serial)
        assert c.status()["calibration_loaded"] == "(none)", serial
        acoustic = p.localizer.calibration_learners()["interference_acoustic"]
        assert acoustic.calibration_state() is None


def test_a_new_device_on_the_same_port_saves_the_old_and_starts_over(tmp_path, device):
    cfg, touches, _, _ = device
    fs = cfg.sample_rate_hz
    pipe = _pipeline(cfg)
    now = [0.0]
    cal = DeviceCalibration(pipe.calibration_learners, str(tmp_path), save_period_s=60.0,
                            clock=lambda: now[0])
    cal.on_device(None)  # not known yet: nothing
    assert cal.store is None and not cal.save_due()
    cal.on_device("A")
    _feed(pipe, touches, fs, 0, 0)
    assert not cal.save_due()  # not yet: 60 s
    now[0] = 61.0
    assert cal.save_due() and (tmp_path / "A.json").exists()
    cal.on_device("B")  # swapped: A saved, the learners start over for B
    assert cal.store.serial == "B"
    learners = pipe.calibration_learners()
    assert all(lr.calibration_state() is None for lr in learners.values()), learners


def test_what_one_body_taught_is_never_loaded_on_another(tmp_path, device):
    """The file is the serial number's on this body (radius, element offset, sound
    speed): the same serial on another body (a fingertip refilled with silicone) starts
    from nothing, and the first body finds its own file again."""
    from ae_tactile.geometry import FingertipGeometry

    cfg, touches, _, _ = device
    fs = cfg.sample_rate_hz
    water = cfg.geometry
    silicone = FingertipGeometry(radius_m=water.radius_m,
                                 element_offset_m=water.element_offset_m,
                                 sound_speed_m_s=1030.0)
    first = _pipeline(cfg)
    cal = DeviceCalibration(first.calibration_learners, str(tmp_path),
                            body=lambda: first.localizer.geometry)
    cal.on_device("AE-0040")
    _feed(first, touches, fs, 0, 0)
    assert cal.close()
    assert cal.store.serial == "AE-0040_R10mm_a1.5mm_c1480"
    other = ContactPipeline(PacketLocalizer("ml", geometry=silicone), None)
    cal2 = DeviceCalibration(other.calibration_learners, str(tmp_path),
                             body=lambda: other.localizer.geometry)
    cal2.on_device("AE-0040")
    assert cal2.store.serial != cal.store.serial
    assert cal2.store.loaded_sections == []
    assert all(lr.calibration_state() is None for lr in other.calibration_learners().values())
    again = _pipeline(cfg)
    cal3 = DeviceCalibration(again.calibration_learners, str(tmp_path),
                             body=lambda: again.localizer.geometry)
    cal3.on_device("AE-0040")
    assert "interference_acoustic" in cal3.store.loaded_sections
    for p in (first, other, again):
        p.close()
