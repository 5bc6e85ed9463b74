"""The sensor benchmark rows (quadswarm_mj.bench.sensor_rows): alternating rounds, median ratios, table."""

from __future__ import annotations

import itertools

from quadswarm_mj.bench.sensor_rows import SENSOR_SETS, TARGETS, measure, sensor_table


def test_measure_alternates_and_takes_median_ratios_of_the_same_round():
    order = []
    speeds = {"off": itertools.cycle([100.0, 50.0, 100.0]), "on": itertools.cycle([80.0, 40.0, 60.0])}

    def runner(name):
        def once():
            order.append(name)
            v = next(speeds[name])
            return v, 2 * v
        return once

    res = measure({"off": runner("off"), "on": runner("on")}, 3)
    assert order == ["off", "on"] * 3  # alternating
    assert res["on"]["ratio"] == 0.8 and res["on"]["ratio_range"] == (0.6, 0.8)  # per-round ratios 0.8, 0.8, 0.6
    assert res["on"]["rate"] == 80.0 and res["off"]["ratio"] == 1.0
    table = sensor_table([{"engine": "E", "sensors": "multiranger + flow", "rounds": 3, **res["on"]}])
    assert "| E | multiranger + flow | 80 | 0.80x (0.60 to 0.80) | 0.80x (0.60 to 0.80) | >= 0.75x |" in table
    assert sensor_table([]) == ""


def test_sets_cover_the_issue_targets():
    names = [name for name, _ in SENSOR_SETS]
    assert names[0] == "off" and set(TARGETS) <= set(names)


def test_part_timings_numpy_rows():
    from quadswarm_mj.bench.sensor_rows import part_timings

    rows = part_timings(reps=2, jax_rows=False)
    labels = [label for label, _ in rows]
    assert "NumPy, 1 x 8, deck part, multiranger + flow" in labels and "NumPy, 1 x 8, axis_hits" in labels
    assert "NumPy, 1 x 8, deck part (perf.numpy_deck), multiranger + flow" in labels
    assert "NumPy, 1 x 8, deck part (perf.numpy_depth), depth 8 x 8" in labels
    assert len(rows) == 8 and all(us > 0 for _, us in rows)
