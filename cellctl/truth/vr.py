"""The `truth` section of a simulated VR run (seed 000): every estimate judged against the hidden world.

For each row with an estimate, the true receptacle-in-ORU pose at the moment its
frames were taken (recorded by the simulated world per frame) gives the true
alignment error; the same statistics as the routine's own (which use the
operator's reference alignment) are then recomputed from those errors. Only runs
on a simulated cell; reads drivers.sim, which calibration/ never does.
"""

from __future__ import annotations

from geometry.transforms import inverse

from calibration.routines.base import Devices, FitOutcome
from calibration.routines.vr._common import INCH, alignment_error
from calibration.routines.vr.vr_experiments import VrExperimentsParams, aggregate, rows_with_errors


def _true_alignment(world, devices: Devices, row: dict):
    frame_id = row.get("side_frame")
    if frame_id is None:
        return None
    camera = devices.cameras.get("side")
    sim_name = getattr(camera, "sim_name", "side")
    truth = world.frame_truth.get((sim_name, int(frame_id)))
    if truth is None:
        return None
    return inverse(truth["receptacle"]) @ truth["oru"]


def vr_truth(world, devices: Devices, params, samples: list[dict], outcome: FitOutcome) -> dict:
    def error_of(row, alignment):
        true = _true_alignment(world, devices, row)
        return None if true is None else alignment_error(alignment, true)

    rows = rows_with_errors(samples, error_of)
    out: dict = {}
    if isinstance(params, VrExperimentsParams):
        stats, _, _ = aggregate(rows, params)
        out.update({k: stats[k] for k in ("alignment", "approach", "covariance_consistency", "view_size") if k in stats})
    else:
        per_row = []
        for r in rows:
            if r.get("status") == "ok" and r.get("pos_err_in") is not None:
                per_row.append({"method": r.get("method"), "stop": r.get("stop"), "distance_in": r.get("distance_in"),
                                "position_in": r["pos_err_in"], "orientation_deg": r["ori_err_deg"],
                                "sigma_pos_in": r.get("sigma_pos_in"), "sigma_ori_deg": r.get("sigma_ori_deg")})
        out["rows"] = per_row
        if per_row:
            out["final"] = per_row[-1]
    out["cameras"] = {name: {"f_px": float(cam.f), "position_m": (-cam.V[:3, :3].T @ cam.V[:3, 3]).tolist()}
                      for name, cam in world.cameras.items()}
    out["receptacle_in"] = (world.receptacle[:3, 3] / INCH).tolist()
    return out

