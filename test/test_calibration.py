# SPDX-License-Identifier: Apache-2.0
"""The per-device calibration file: what learners saved comes back after a restart, a
reset starts from scratch, damaged files and unusable sections are counted and set aside,
writes are atomic, and a serial number cannot name a path elsewhere."""

import json
import os

from ae_tactile.calibration import FORMAT_VERSION, CalibrationStore, default_directory, file_name


class Mean:
    """A learner: the running mean of what it saw, usable from 5 samples."""

    def __init__(self):
        self.values = []

    def add(self, x):
        self.values.append(float(x))

    def calibration_state(self):
        return {"values": self.values[-50:]} if len(self.values) >= 5 else None

    def load_calibration(self, state):
        v = state["values"]
        if not isinstance(v, list) or not all(isinstance(x, (int, float)) for x in v):
            raise ValueError("values must be numbers")
        self.values = [float(x) for x in v]


def test_what_a_device_taught_comes_back_after_a_restart(tmp_path):
    a, b = Mean(), Mean()
    for x in range(10):
        a.add(x)
    b.add(1.0)  # too little learnt: not written
    store = CalibrationStore(str(tmp_path / "cal"), "AE-0042")
    assert store.save({"pulse": a, "noise": b})
    doc = json.loads(open(store.path).read())
    assert doc["format"] == FORMAT_VERSION and doc["serial"] == "AE-0042"
    assert set(doc["sections"]) == {"pulse"}
    again = Mean()
    fresh = CalibrationStore(str(tmp_path / "cal"), "AE-0042")
    assert fresh.load_into({"pulse": again, "noise": Mean()}) == ["pulse"]
    assert again.values == a.values
    other = CalibrationStore(str(tmp_path / "cal"), "AE-0043")  # another device: its own
    assert other.load_into({"pulse": Mean()}) == []


def test_reset_ignores_the_file_and_the_next_save_replaces_it(tmp_path):
    a = Mean()
    for x in range(10):
        a.add(x)
    CalibrationStore(str(tmp_path), "S1").save({"pulse": a})
    store = CalibrationStore(str(tmp_path), "S1", reset=True)
    m = Mean()
    assert store.load_into({"pulse": m}) == [] and m.values == []
    for x in range(5):
        m.add(100 + x)
    assert store.save({"pulse": m})
    n = Mean()
    CalibrationStore(str(tmp_path), "S1").load_into({"pulse": n})
    assert n.values == [100.0, 101.0, 102.0, 103.0, 104.0]
    assert store.delete() and not os.path.exists(store.path) and not store.delete()


def test_a_damaged_file_is_set_aside_counted_and_learnt_again(tmp_path):
    store = CalibrationStore(str(tmp_path), "S2")
    for text in ("{not json", json.dumps({"format": 99, "sections": {}}),
                 json.dumps({"format": FORMAT_VERSION, "sections": {"pulse": [1, 2]}}),
                 "\udcff"):
        with open(store.path, "w", encoding="utf-8", errors="surrogateescape") as fh:
            fh.write(text)
        m = Mean()
        assert store.load_into({"pulse": m}) == [] and m.values == []
        assert os.path.exists(store.path + ".bad") and not os.path.exists(store.path)
    assert store.counts["files_damaged"] == 4 and store.last_error


def test_an_unusable_section_is_rejected_alone(tmp_path):
    store = CalibrationStore(str(tmp_path), "S3")
    doc = {"format": FORMAT_VERSION, "serial": "S3",
           "sections": {"pulse": {"values": ["x"]}, "noise": {"values": [1.0, 2.0]}}}
    with open(store.path, "w") as fh:
        json.dump(doc, fh)
    p, n = Mean(), Mean()
    assert store.load_into({"pulse": p, "noise": n}) == ["noise"]
    assert p.values == [] and n.values == [1.0, 2.0]
    assert store.counts["sections_rejected"] == 1 and "pulse" in store.last_error


def test_a_failed_write_keeps_the_previous_file(tmp_path):
    a = Mean()
    for x in range(6):
        a.add(x)
    store = CalibrationStore(str(tmp_path), "S4")
    assert store.save({"pulse": a})
    before = open(store.path).read()

    class Bad(Mean):
        def calibration_state(self):
            return {"values": [float("nan")] * 5}  # not JSON: refused before the file

    assert not store.save({"pulse": Bad()})
    assert open(store.path).read() == before and store.counts["save_errors"] == 1
    assert [f for f in os.listdir(tmp_path) if f.startswith(".calibration-")] == []


def test_a_serial_number_cannot_name_a_path_elsewhere(tmp_path, monkeypatch):
    assert file_name("../../etc/passwd") == "_.._etc_passwd.json"
    assert "/" not in file_name("a/b") and file_name("") == "unknown.json"
    assert len(file_name("x" * 1000)) <= 125
    store = CalibrationStore(str(tmp_path), "../escape")
    assert os.path.dirname(store.path) == str(tmp_path)
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "rh"))
    assert default_directory() == str(tmp_path / "rh" / "ae_tactile" / "calibration")
