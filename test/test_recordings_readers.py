# SPDX-License-Identifier: Apache-2.0
"""Recording readers: WAV (integer PCM and float, any channel count), CSV (time column or a
given rate), NPY / NPZ (both orientations, the simulator's own .npz), and a clear error
naming the file for every kind of bad file."""

import numpy as np
import pytest
from scipy.io import wavfile

from ae_tactile.recordings import RecordingError, read_recording
from ae_tactile.recordings.readers import detect_format

FS = 1_000_000.0


def _signal(n_channels=3, n=2000, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.5, 0.5, (n_channels, n))


def test_int16_wav_is_scaled_to_the_full_scale_given_and_says_so(tmp_path):
    x = _signal(3)
    codes = np.round(x * 32767).astype(np.int16)
    path = tmp_path / "three.wav"
    wavfile.write(path, int(FS), codes.T)
    (rec,) = read_recording(path)
    assert rec.samples_v.shape == (3, 2000) and rec.sample_rate_hz == FS
    np.testing.assert_allclose(rec.samples_v, codes / 32768.0)
    assert any("1 V" in n and "default" in n for n in rec.notes)
    (rec2,) = read_recording(path, full_scale_v=2.5)
    np.testing.assert_allclose(rec2.samples_v, codes * 2.5 / 32768.0)
    assert any("given" in n for n in rec2.notes)


@pytest.mark.parametrize("n_channels", [1, 2, 7])
def test_float_wav_is_volts_as_stored_for_any_channel_count(tmp_path, n_channels):
    x = _signal(n_channels).astype(np.float32)
    path = tmp_path / "f.wav"
    wavfile.write(path, 2_000_000, x.T if n_channels > 1 else x[0])
    (rec,) = read_recording(path)
    assert rec.n_channels == n_channels and rec.sample_rate_hz == 2e6
    np.testing.assert_array_equal(rec.samples_v, x.astype(np.float64))
    assert rec.channels == tuple(range(n_channels)) and rec.pretrigger_samples == 0


def test_uint8_and_int32_wav(tmp_path):
    u8 = np.array([0, 128, 255, 64], np.uint8)
    wavfile.write(tmp_path / "u8.wav", 44100, u8)
    (rec,) = read_recording(tmp_path / "u8.wav", full_scale_v=1.0)
    np.testing.assert_allclose(rec.samples_v[0], [-1.0, 0.0, 127 / 128, -0.5])
    i32 = np.array([[-2**31, 2**30], [0, 2**31 - 1]], np.int32)
    wavfile.write(tmp_path / "i32.wav", 44100, i32)
    (rec,) = read_recording(tmp_path / "i32.wav")
    np.testing.assert_allclose(rec.samples_v, [[-1.0, 0.0], [0.5, (2**31 - 1) / 2**31]])


def test_csv_with_a_time_column_takes_rate_start_and_channel_names(tmp_path):
    x = _signal(2, 500)
    t = 0.25 + np.arange(500) / FS
    path = tmp_path / "rec.csv"
    with path.open("w") as fh:
        fh.write("# exported by a scope\nTime,ch_a,ch_b\n")
        for i in range(500):
            fh.write(f"{t[i]:.9f},{x[0, i]:.9g},{x[1, i]:.9g}\n")
    (rec,) = read_recording(path)
    assert rec.sample_rate_hz == pytest.approx(FS, rel=1e-9)
    assert rec.start_time_s == pytest.approx(0.25) and rec.channels == ("ch_a", "ch_b")
    np.testing.assert_allclose(rec.samples_v, x, rtol=1e-8)


def test_csv_without_time_column_needs_the_rate_and_reads_semicolons(tmp_path):
    x = _signal(4, 100)
    path = tmp_path / "plain.csv"
    path.write_text("\n".join(";".join(f"{v:.6f}" for v in row) for row in x.T) + "\n")
    with pytest.raises(RecordingError, match="plain.csv.*no time column.*no sample rate"):
        read_recording(path)
    (rec,) = read_recording(path, sample_rate_hz=5e6)
    assert rec.samples_v.shape == (4, 100) and rec.sample_rate_hz == 5e6
    np.testing.assert_allclose(rec.samples_v, x, atol=1e-6)


def test_npy_in_either_orientation_and_npz_with_its_metadata(tmp_path):
    x = _signal(4, 300)
    np.save(tmp_path / "cm.npy", x)
    np.save(tmp_path / "sm.npy", x.T.astype(np.float32))
    for name in ("cm.npy", "sm.npy"):
        (rec,) = read_recording(tmp_path / name, sample_rate_hz=FS)
        assert rec.samples_v.shape == (4, 300)
        np.testing.assert_allclose(rec.samples_v, x, rtol=1e-6)
    with pytest.raises(RecordingError, match="cm.npy.*no sample rate"):
        read_recording(tmp_path / "cm.npy")
    np.savez(tmp_path / "meta.npz", samples_v=x, sample_rate_hz=2e6, pretrigger_samples=50,
             start_time_s=1.5, channels=np.array(["a", "b", "c", "d"]))
    (rec,) = read_recording(tmp_path / "meta.npz", sample_rate_hz=123.0)
    assert rec.sample_rate_hz == 2e6 and rec.pretrigger_samples == 50
    assert rec.start_time_s == 1.5 and rec.channels == ("a", "b", "c", "d")


def test_the_simulator_cli_npz_reads_as_volts(tmp_path):
    """`ae_tactile.sim.cli` stores ADC codes with their lsb_v and start_time_ns."""
    codes = np.array([[1, -2, 3], [0, 5, -5]], np.int16)
    np.savez(tmp_path / "sim.npz", samples=codes, lsb_v=np.float64(0.5 / 2048),
             sample_rate_hz=np.float64(1e7), start_time_ns=np.int64(2_000_000_000))
    (rec,) = read_recording(tmp_path / "sim.npz")
    np.testing.assert_allclose(rec.samples_v, codes * (0.5 / 2048))
    assert rec.start_time_s == 2.0 and rec.sample_rate_hz == 1e7


@pytest.mark.parametrize("name, content, match", [
    ("garbage.wav", b"RIFF\x00\x00garbage", "garbage.wav: not a readable WAV"),
    ("empty.csv", b"", "empty.csv: fewer than 2 data rows"),
    ("words.csv", b"a,b\n1,2\nx,y\n", r"words.csv: row 3 is not numeric"),
    ("bin.csv", b"\x00\x01\x02" * 50, "bin.csv: binary content"),
    ("ragged.csv", b"1,2\n3\n4,5\n", "ragged.csv: rows have different numbers of columns"),
    ("header.csv", b"a,b,c\n1,2\n3,4\n", "header.csv: rows have different numbers"),
    ("oneline.csv", b"t,v\n1,2\n", "oneline.csv: fewer than 2 data rows"),
    ("nonuniform.csv", b"time,v\n0,1\n1e-6,2\n3e-6,3\n4e-6,4\n", "not uniformly sampled"),
    ("backwards.csv", b"t,v\n0,1\n2e-6,2\n1e-6,3\n", "not strictly increasing"),
    ("broken.npy", b"\x93NUMPY garbage", "broken.npy: not a readable NPY"),
    ("noise.tradb", b"not sqlite at all" * 10, "noise.tradb: not a readable Vallen tradb"),
    ("rec.xyz", b"1,2\n", "rec.xyz: unknown recording format"),
])
def test_bad_files_give_a_clear_error_naming_the_file(tmp_path, name, content, match):
    if name.endswith(".tradb"):
        pytest.importorskip("vallenae", reason="vallenae (optional) reads Vallen files")
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=match):
        read_recording(path, sample_rate_hz=FS)


def test_bad_contents_and_settings(tmp_path):
    with pytest.raises(RecordingError, match="missing.wav: no such file"):
        read_recording(tmp_path / "missing.wav")
    x = _signal(2, 10)
    x[1, 3] = np.nan
    np.save(tmp_path / "nan.npy", x)
    with pytest.raises(RecordingError, match="nan.npy: 1 samples are NaN"):
        read_recording(tmp_path / "nan.npy", sample_rate_hz=FS)
    np.save(tmp_path / "ok.npy", _signal(2, 10))
    for fs in (0.0, -1.0, float("nan"), 1e13, "fast"):
        with pytest.raises(RecordingError, match="ok.npy: sample rate"):
            read_recording(tmp_path / "ok.npy", sample_rate_hz=fs)
    np.save(tmp_path / "obj.npy", np.array(["a", "b"]))
    with pytest.raises(RecordingError, match="obj.npy: samples must be a 1-D or 2-D numeric"):
        read_recording(tmp_path / "obj.npy", sample_rate_hz=FS)
    np.savez(tmp_path / "two.npz", a=np.zeros(5), b=np.zeros(5))
    with pytest.raises(RecordingError, match="two.npz: no 'samples_v' or 'samples'"):
        read_recording(tmp_path / "two.npz", sample_rate_hz=FS)
    wavfile.write(tmp_path / "i16.wav", 1000, np.zeros(10, np.int16))
    with pytest.raises(RecordingError, match="i16.wav: full_scale_v must be > 0"):
        read_recording(tmp_path / "i16.wav", full_scale_v=0.0)
    with pytest.raises(RecordingError, match="unknown format 'mp3'"):
        read_recording(tmp_path / "i16.wav", format="mp3")
    assert detect_format("a.PRIDB") == "vallen" and detect_format("b.npz") == "npy"
