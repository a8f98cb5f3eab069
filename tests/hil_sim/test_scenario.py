"""Scenario files: segments, repeat groups, feeds, ambient, and clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil_sim.scenario import Ambient, Scenario

SCENARIOS = Path(__file__).resolve().parents[2] / "hil_sim" / "scenarios"


def test_repeat_groups_expand_and_segment_lookup():
    sc = Scenario.from_dict(
        {
            "machine": "feed_axis",
            "params": {"dt_s": 2.0},
            "segments": [
                {"duration_s": 100, "pos_mm": 0},
                {
                    "repeat": 3,
                    "segments": [
                        {"duration_s": 10, "feed_mm_min": 6000, "stroke_mm": [0, 300]},
                        {"duration_s": 5, "axis_load": {"x2": 1.3}},
                    ],
                },
            ],
        }
    )
    assert len(sc.segments) == 7
    assert sc.duration_s == 145.0
    assert sc.machine == "feed_axis" and sc.params == {"dt_s": 2.0}
    assert sc.segment_at(0.0).pos_mm == 0
    assert sc.segment_at(100.0).feed_mm_min == 6000
    assert sc.segment_at(112.0).load_of("x2") == pytest.approx(1.3)
    assert sc.segment_at(1e9) is sc.segments[-1]
    # groups are copies, not shared objects
    sc.segments[2].axis_load["x2"] = 9.0
    assert sc.segments[4].axis_load["x2"] == 1.3


def test_ambient_drift_sine_and_points():
    amb = Ambient(
        start_c=20.0, drift_c_per_h=0.1, daily_amplitude_c=1.0, daily_phase_h=0.0, points=[[0, 0.0], [2, 1.0]]
    )
    assert amb.at(0.0) == pytest.approx(20.0)
    assert amb.at(3600.0) == pytest.approx(20.0 + 0.1 + 0.2588190451 + 0.5, abs=1e-6)
    assert amb.at(6 * 3600.0) == pytest.approx(20.0 + 0.6 + 1.0 + 1.0)


@pytest.mark.parametrize(
    ("data", "needle"),
    [
        ({"segments": []}, "segments"),
        ({"segments": [{"duration_s": 10, "sped_rpm": 3}]}, "segments[0].sped_rpm"),
        ({"segments": [{"duration_s": -1}]}, "segments[0].duration_s"),
        ({"segments": [{"speed_rpm": 100}]}, "segments[0].duration_s"),
        ({"segments": [{"duration_s": 5, "speed_rpm": "fast"}]}, "segments[0].speed_rpm"),
        ({"segments": [{"duration_s": 5, "stroke_mm": [300, 0]}]}, "segments[0].stroke_mm"),
        ({"segments": [{"repeat": 0, "segments": [{"duration_s": 1}]}]}, "segments[0].repeat"),
        ({"segments": [{"duration_s": 5}], "ambient": {"start": 3}}, "ambient.start"),
        ({"segments": [{"duration_s": 5}], "colour": 1}, "colour"),
    ],
)
def test_bad_scenarios_name_the_key(data, needle):
    with pytest.raises(ValueError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        Scenario.from_dict(data)


def test_load_names_the_file_and_line(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("machine: lathe\nsegments: [\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"bad\.yaml:\d+: not valid YAML"):
        Scenario.load(f)


def test_shipped_scenarios_load_and_last_a_day():
    files = sorted(SCENARIOS.glob("*_train.yaml")) + sorted(SCENARIOS.glob("*_unseen.yaml"))
    machines = set()
    for f in files:
        sc = Scenario.load(f)
        machines.add(sc.machine)
        assert sc.duration_s == pytest.approx(86400.0), f.name
    assert machines == {"lathe", "spindle", "gantry", "feed_axis", "vmc"}
    assert len(files) == 10
