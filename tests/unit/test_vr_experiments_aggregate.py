"""The VR experiments' report from its samples: a method whose every Fig. 7 run failed is reported as failed,
with no spread, instead of failing the whole report."""

import numpy as np

from calibration.routines.vr._samples import ERROR_COLUMNS
from calibration.routines.vr.vr_experiments import INCH, METHODS, VrExperimentsParams, aggregate


def test_a_method_whose_every_run_failed_is_reported_with_no_spread():
    rows = [{"kind": "fig7", "method": m, "status": "failed", "run": i} for m in METHODS for i in range(3)]
    stats, tables, _ = aggregate(rows, VrExperimentsParams())
    for m in METHODS:
        summary = stats["alignment"][m]
        assert summary["n"] == 0 and summary["n_failed"] == 3
        assert summary["position_in"] is None and summary["rms_position_in"] is None
    assert "gain_over_objloc12" not in stats["alignment"]
    fig7 = tables[0]["rows"]
    assert [row[6:8] for row in fig7[:len(METHODS)]] == [[0, 3]] * len(METHODS)  # runs, failed


def test_one_run_has_no_spread_and_two_have_one():
    def run(i, err):
        return {"kind": "fig7", "method": "simultaneous", "status": "ok", "run": i, **dict(zip(ERROR_COLUMNS, err)),
                "pos_err_in": err[0] / INCH, "ori_err_deg": 0.0, "sigma_pos_in": None, "sigma_ori_deg": None}

    one = aggregate([run(0, [1e-4, 0, 0, 0, 0, 0])], VrExperimentsParams())[0]["alignment"]["simultaneous"]
    assert one["n"] == 1 and one["position_in"] is None
    two = aggregate([run(0, [1e-4, 0, 0, 0, 0, 0]), run(1, [3e-4, 0, 0, 0, 0, 0])],
                    VrExperimentsParams())[0]["alignment"]["simultaneous"]
    assert two["n"] == 2 and np.isclose(two["position_in"], np.std([1e-4, 3e-4], ddof=1) / INCH)
