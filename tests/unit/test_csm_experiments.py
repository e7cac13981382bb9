"""Table V's choice of k per weighting scheme."""

from calibration.routines.csm._experiments import VW_SCHEMES, best_k


def test_the_smallest_error_wins_and_a_tie_to_rounding_goes_to_the_smallest_k():
    sweep = {s: {1.0: 0.030, 2.0: 0.020, 3.0: 0.025} for s in VW_SCHEMES}
    sweep["w1"] = {1.0: 0.0206320000001, 3.0: 0.0206320000000, 5.0: 0.0206320000002}  # k only scales w1
    best = best_k(sweep)
    assert best["w1"] == 1.0
    assert all(best[s] == 2.0 for s in VW_SCHEMES if s != "w1")
