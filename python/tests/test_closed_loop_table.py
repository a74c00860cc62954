"""tools/closed_loop_table.py's paired comparison: one collision moves a six-scenario mean by ~0.17, so "b2dr above
masks-only" is judged by the per-scenario paired difference and its bootstrap interval, over `--seeds` scenarios."""
import numpy as np
import pytest



@pytest.fixture(scope="module")
def clt(tool):
    return tool("closed_loop_table")


def test_seeds_expand_to_the_six_layouts_dense_per_seed(clt):
    s = clt.seed_scenarios("100-101").split(",")
    assert len(s) == 12
    assert s[0] == "builtin:town:100:60" and s[5] == "builtin:multilane:100:60" and s[6] == "builtin:town:101:60"
    assert clt.seed_scenarios("104") == ",".join(f"builtin:{lay}:104:60" for lay in clt.LAYOUTS)
    assert clt.seed_scenarios("100,103").split(",")[6] == "builtin:town:103:60"
    for bad in ["a-b", "103-100", "1-2-3", ""]:
        with pytest.raises(SystemExit):
            clt.seed_scenarios(bad)


def test_paired_difference_against_a_direct_bootstrap(clt):
    rng = np.random.default_rng(3)
    a, b = rng.uniform(0.8, 1.0, 18), rng.uniform(0.8, 1.0, 18)
    a[4] = b[4]
    p = clt.paired_difference(a, b, resamples=4000, seed=7)
    d = a - b
    # the same bootstrap written out: resample scenarios with replacement, percentile interval
    r = np.random.default_rng(7)
    means = np.array([d[r.integers(0, 18, size=18)].mean() for _ in range(4000)])
    assert p["mean"] == pytest.approx(d.mean(), abs=1e-15)
    assert p["lo"] == pytest.approx(np.percentile(means, 2.5), abs=1e-12)
    assert p["hi"] == pytest.approx(np.percentile(means, 97.5), abs=1e-12)
    assert p["lo"] < p["mean"] < p["hi"]
    assert (p["wins"], p["losses"], p["ties"]) == ((d > 0).sum(), (d < 0).sum(), 1)
    assert p["n"] == 18


def test_one_collision_among_six_is_not_separable_but_a_consistent_gain_is(clt):
    # five scenarios equal, one crashed (the `straight` seed 100 pattern): the mean is -0.17, but the interval
    # reaches 0, so the table must not read it as "below"
    a, b = [1.0, 0.99, 0.98, 0.99, 1.0, 0.0], [1.0, 0.99, 0.98, 0.99, 1.0, 1.0]
    p = clt.paired_difference(a, b)
    assert p["mean"] == pytest.approx(-1 / 6)
    assert clt.verdict(p) == "not separable (interval contains 0)"
    # a small gain on every one of 18 scenarios is separable
    q = clt.paired_difference(np.full(18, 0.95) + np.linspace(0, 0.01, 18), np.full(18, 0.94))
    assert clt.verdict(q) == "above (interval excludes 0)"
    assert clt.verdict(clt.paired_difference([0.1, 0.2], [0.5, 0.6])) == "below (interval excludes 0)"


def test_paired_rows_compare_b2dr_with_every_other_renderer_and_refuse_bad_input(clt):
    rows = clt.paired_rows({"b2dr": [1, 0.5], "masks": [0.5, 0.5], "log-replay": [1, 1]})
    assert [r["renderer"] for r in rows] == ["masks", "log-replay"]
    assert rows[0]["mean"] == pytest.approx(0.25) and rows[1]["mean"] == pytest.approx(-0.25)
    assert clt.paired_rows({"masks": [1.0]}) == []
    with pytest.raises(ValueError):
        clt.paired_difference([1.0, 2.0], [1.0])
    with pytest.raises(ValueError):
        clt.paired_difference([], [])
