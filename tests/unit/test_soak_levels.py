"""src/lrfslam/bench/soak.py reads memory as a level, not a sample: a transient peak is not growth, a step is."""

from __future__ import annotations


def _result(soak, samples: dict[str, list[tuple[float, int]]]):
    series = {name: soak.Series(name, [(t, kb, 1) for t, kb in rows]) for name, rows in samples.items()}
    return soak.SoakResult(["python", "-m", "lrfslam.cli", "up"], 1000, 10.0, 0, "", series, (0.0, 100.0),
                           {}, 1000, 1000, 0)


def test_a_peak_in_the_last_sample_is_not_growth(soak_module):
    soak = soak_module
    flat_with_peak = [(float(t), 100_000) for t in range(0, 100, 5)] + [(100.0, 140_000)]
    result = _result(soak, {"mapper": flat_with_peak})
    assert result.rss_between(0.1, window_s=30.0) == {"mapper": (100_000, 100_000)}
    assert result.series["mapper"].peak(10.0, 100.0) == 140_000
    assert not [p for p in result.problems(0.1, 10.0, window_s=30.0) if "RSS" in p]


def test_a_step_that_stays_is_growth(soak_module):
    soak = soak_module
    step = [(float(t), 100_000 if t < 50 else 120_000) for t in range(0, 101, 5)]
    result = _result(soak, {"recorder": step})
    assert result.rss_between(0.1, window_s=30.0) == {"recorder": (100_000, 120_000)}
    assert [p for p in result.problems(0.1, 10.0, window_s=30.0) if p.startswith("recorder: RSS grew 20.0 %")]


def test_a_window_with_no_sample_takes_the_last_one_before(soak_module):
    soak = soak_module
    sparse = [(0.0, 90_000), (40.0, 100_000), (100.0, 105_000)]
    result = _result(soak, {"slam": sparse})
    assert result.series["slam"].level(60.0, 70.0) == 100_000
    assert result.series["slam"].level(-11.0, -1.0) is None


def test_warm_up_is_read_after_it_ends_and_the_end_before_it(soak_module):
    soak = soak_module
    # A one-time step just before warm-up ends (the mapper's first wide search) is warm-up, not growth.
    step_then_flat = [(float(t), 100_000 if t < 8 else 130_000) for t in range(0, 101, 2)]
    result = _result(soak, {"mapper": step_then_flat})
    assert result.rss_between(0.1, window_s=30.0) == {"mapper": (130_000, 130_000)}
    # The two windows never overlap: each is at most half of the span compared.
    rising = [(float(t), 100_000 + 100 * t) for t in range(101)]
    first, last = _result(soak, {"slam": rising}).rss_between(0.5, window_s=1000.0)["slam"]
    assert (first, last) == (106_250, 108_750)   # medians of [50, 75] s and [75, 100] s
