# SPDX-License-Identifier: Apache-2.0
"""The PNG run summary: a real PNG of the requested size, what is drawn follows the input,
empty input and NaN handled, bad input refused with a clear error."""
import math
import struct
import zlib

import numpy as np
import pytest

from ae_tactile.report import EVENT_TYPES, STYLE, write_run_summary

pytest.importorskip("matplotlib", reason="matplotlib not installed: PNG summaries unavailable")


def read_png(path):
    """(width, height, RGBA uint8 array) decoded with zlib alone (8-bit RGB/RGBA PNG)."""
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG file"
    pos, chunks = 8, []
    width = height = bit_depth = colour_type = None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        crc = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])[0]
        assert zlib.crc32(kind + body) == crc, f"bad CRC in {kind!r}"
        if kind == b"IHDR":
            width, height, bit_depth, colour_type = struct.unpack(">IIBB", body[:10])
        elif kind == b"IDAT":
            chunks.append(body)
        pos += 12 + length
    assert bit_depth == 8 and colour_type in (2, 6), (bit_depth, colour_type)
    channels = 4 if colour_type == 6 else 3
    raw = zlib.decompress(b"".join(chunks))
    stride = width * channels
    img = np.zeros((height, stride), dtype=np.uint8)
    prev = np.zeros(stride, dtype=np.int32)
    for y in range(height):                      # PNG row filters (test-size images only)
        f = raw[y * (stride + 1)]
        row = np.frombuffer(raw, np.uint8, stride, y * (stride + 1) + 1).astype(np.int32)
        out = np.zeros(stride, dtype=np.int32)
        for x in range(stride):
            a = out[x - channels] if x >= channels else 0
            b = prev[x]
            c = prev[x - channels] if x >= channels else 0
            if f == 0:
                pred = 0
            elif f == 1:
                pred = a
            elif f == 2:
                pred = b
            elif f == 3:
                pred = (a + b) // 2
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            out[x] = (row[x] + pred) & 0xFF
        img[y] = out
        prev = out
    return width, height, img.reshape(height, width, channels)


def colour_pixels(img, hex_colour, tol=6):
    rgb = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])
    return int((np.abs(img[..., :3].astype(int) - rgb).max(axis=-1) <= tol).sum())


def events_of(kinds, rng):
    n = len(kinds)
    theta = rng.uniform(0.1, 1.2, n)
    phi = rng.uniform(-math.pi, math.pi, n)
    r = 0.01
    return [{"time_s": 0.01 * i, "type": k, "x_m": r * math.sin(t) * math.cos(p),
             "y_m": r * math.sin(t) * math.sin(p), "z_m": r * math.cos(t),
             "latency_s": 1e-3 + 1e-4 * i}
            for i, (k, t, p) in enumerate(zip(kinds, theta, phi))]


SIZE = (400, 260)     # small: the pure-Python PNG decoder above stays quick


def test_png_has_the_requested_size_and_shows_the_event_types_given(tmp_path):
    rng = np.random.default_rng(1)
    events = events_of(["TOUCH"] * 5 + ["SLIP"] * 3, rng)
    out = write_run_summary(tmp_path / "run.png", events, truth=[{"x_m": 0.0, "y_m": 0.0}],
                            contact_state=[{"time_s": 0.0, "state": "STICK"},
                                           {"time_s": 0.05, "state": "SLIP"}],
                            size_px=SIZE, dpi=50)
    w, h, img = read_png(out["path"])
    assert (w, h) == SIZE
    assert out["events"] == 8 and out["events_plotted"] == 8 and out["truth_points"] == 1
    assert out["latencies"] == 8
    lat = np.array([e["latency_s"] for e in events])
    assert out["latency_median_s"] == pytest.approx(np.median(lat))
    assert colour_pixels(img, STYLE["TOUCH"][0]) > 0 and colour_pixels(img, STYLE["SLIP"][0]) > 0
    assert colour_pixels(img, STYLE["TEXTURE"][0]) == 0      # none given, none drawn


def test_empty_input_still_writes_the_figure(tmp_path):
    out = write_run_summary(tmp_path / "empty.png", [], size_px=SIZE, dpi=50)
    w, h, img = read_png(out["path"])
    assert (w, h) == SIZE
    assert out["events"] == 0 and out["latencies"] == 0 and math.isnan(out["latency_median_s"])
    for name in EVENT_TYPES:
        assert colour_pixels(img, STYLE[name][0]) == 0
    assert (img[..., :3] < 128).any()                   # axes and text are drawn


def test_nan_rows_are_counted_and_left_out_of_the_panels_that_need_them(tmp_path):
    cols = {"time_s": np.array([0.0, 0.1, np.nan, 0.3]),
            "type": np.array([1, 2, 1, 3]),               # ContactEvent numbers work too
            "x_m": np.array([0.001, np.nan, 0.002, 0.0]),
            "y_m": np.array([0.0, 0.001, 0.002, np.nan]),
            "z_m": np.array([0.0099, 0.0099, 0.0095, 0.0099]),
            "latency_s": np.array([1e-3, np.nan, 2e-3, np.inf])}
    out = write_run_summary(tmp_path / "nan.png", cols, size_px=SIZE, dpi=50)
    assert out["events"] == 4
    assert out["events_plotted"] == 2 and out["events_without_position"] == 2
    assert out["events_without_time"] == 1 and out["latencies"] == 2
    assert read_png(out["path"])[:2] == SIZE


@pytest.mark.parametrize("events, words", [
    ([{"time_s": 0.0}], ["type"]),                                       # missing column
    ([{"time_s": 0.0, "type": "POKE"}], ["POKE", "TOUCH"]),              # unknown type
    ({"time_s": np.zeros((2, 2)), "type": np.ones(2)}, ["time_s", "1-D"]),
    ({"time_s": np.zeros(3), "type": np.ones(2)}, ["type", "rows"]),
    ([{"time_s": "soon", "type": "TOUCH"}], ["time_s", "numeric"]),
    ([42], ["row 0"]),
])
def test_bad_input_is_a_clear_error(tmp_path, events, words):
    with pytest.raises(ValueError) as err:
        write_run_summary(tmp_path / "bad.png", events, size_px=SIZE, dpi=50)
    assert all(w in str(err.value) for w in words), str(err.value)
    assert not (tmp_path / "bad.png").exists()


def test_bad_geometry_or_size_is_refused(tmp_path):
    with pytest.raises(ValueError, match="radius_m"):
        write_run_summary(tmp_path / "g.png", [], radius_m=float("nan"))
    with pytest.raises(ValueError, match="element_offset_m"):
        write_run_summary(tmp_path / "g.png", [], radius_m=0.01, element_offset_m=0.02)
    with pytest.raises(ValueError, match="size_px"):
        write_run_summary(tmp_path / "g.png", [], size_px=(10, 10))


def test_the_true_state_is_drawn_under_the_reported_one(tmp_path):
    """Given the true state's changes, the timeline gets a row of its own: a state only the
    truth holds (INCIPIENT_SLIP here) is drawn in its colour; without the truth it is not."""
    from ae_tactile.report import STATE_COLOURS

    events = events_of(["TOUCH", "SLIP"], np.random.default_rng(3))
    reported = [{"time_s": 0.0, "state": "STICK"}, {"time_s": 0.01, "state": "GROSS_SLIP"}]
    truth = [{"time_s": 0.0, "state": "INCIPIENT_SLIP"}, {"time_s": 0.01, "state": "GROSS_SLIP"}]
    emissions = [{"x_m": 1e-3, "y_m": -2e-3, "time_s": 0.0}, {"x_m": math.nan, "y_m": 0.0}]
    with_truth = write_run_summary(tmp_path / "t.png", events, contact_state=reported,
                                   truth_state=truth, emissions=emissions, size_px=SIZE, dpi=50)
    without = write_run_summary(tmp_path / "n.png", events, contact_state=reported,
                                size_px=SIZE, dpi=50)
    inc = STATE_COLOURS["INCIPIENT_SLIP"]
    assert colour_pixels(read_png(with_truth["path"])[2], inc, tol=2) > 0
    assert colour_pixels(read_png(without["path"])[2], inc, tol=2) == 0
    assert with_truth["emissions_plotted"] == 1 and without["emissions_plotted"] == 0
