"""csm-positioning's sample set: what a row is, rows grouped into sampled poses, and those poses read as
CSM's (nominal 3D, camera-space) samples.

Samples CSV (one row per camera and feature; `fit` needs only `FIT_COLUMNS`, the rest is bookkeeping):
  step      step index; rows of one step are one pose (offline files without it: one pose per distinct joints)
  phase     survey | approach | iterate (default survey)
  target    target index (survey and the loops of that target)
  loop      `mode:scheme` of an iterate row
  iteration iteration index within its loop
  status    ok | no-marks | converged | skipped | failed (only ok rows carry a sample)
  camera    camera name; feature: white | black1 | black2 | black3 (default white)
  u_px, v_px            the mark's centre by the chosen detector; u_alt_px, v_alt_px: the other detector
  width_px, height_px   image size (flattening scales about the image centre)
  j1_deg .. j6_deg      joints reported by the controller
  k, correction_mm, pred_x_mm, pred_y_mm, pred_z_mm   the loop's estimate behind the move
"""

from __future__ import annotations

import numpy as np

from calibration.errors import CalibrationInputError
from calibration.models import csm
from calibration.models.irb120 import Kinematics

FEATURES = ("white", "black1", "black2", "black3")
BLACKS = FEATURES[1:]
JOINT_COLS = tuple(f"j{i}_deg" for i in range(1, 7))
SAMPLE_COLUMNS = (
    "step", "phase", "target", "loop", "iteration", "status", "camera", "feature", "frame_id",
    "u_px", "v_px", "u_alt_px", "v_alt_px", "width_px", "height_px", *JOINT_COLS,
    "k", "correction_mm", "pred_x_mm", "pred_y_mm", "pred_z_mm", "message",
)
FIT_COLUMNS = ("camera", "u_px", "v_px", *JOINT_COLS)


class SampledPose:
    """One sampled pose: joints (rad) and per camera, per feature, the mark's centre."""

    __slots__ = ("joints", "loop", "phase", "size", "step", "target", "uv")

    def __init__(self, step, phase, target, loop, joints):
        self.step, self.phase, self.target, self.loop, self.joints = step, phase, target, loop, joints
        self.uv: dict[str, dict[str, np.ndarray]] = {}
        self.size: dict[str, tuple[float, float]] = {}


class SampleSet:
    """The samples as poses, from rows (live history or an offline CSV)."""

    def __init__(self, poses: list[SampledPose]):
        self.poses = poses
        self.by_target: dict[int, SampledPose] = {p.target: p for p in poses if p.phase == "survey"}

    @classmethod
    def from_rows(cls, rows) -> SampleSet:
        poses: dict = {}
        for r in rows:
            if r.get("status", "ok") != "ok" or r.get("u_px") is None:
                continue
            joints = tuple(float(r[c]) for c in JOINT_COLS)
            key = r["step"] if r.get("step") is not None else joints
            phase = r.get("phase") or "survey"
            pose = poses.get(key)
            if pose is None:
                target = r.get("target")
                if target is None and phase == "survey":
                    target = len([p for p in poses.values() if p.phase == "survey"])
                pose = poses[key] = SampledPose(key, phase, target, r.get("loop"), np.radians(joints))
            cam = str(r["camera"])
            pose.uv.setdefault(cam, {})[r.get("feature") or "white"] = np.array([float(r["u_px"]), float(r["v_px"])])
            if r.get("width_px") is not None:
                pose.size[cam] = (float(r["width_px"]), float(r["height_px"]))
        return cls(list(poses.values()))

    def cameras(self) -> list[str]:
        return sorted({c for p in self.poses for c in p.uv})

    def survey(self) -> list[SampledPose]:
        return [p for p in self.poses if p.phase == "survey"]

    def target_uv(self, t: int, cameras) -> list[np.ndarray]:
        pose = self.by_target.get(t)
        if pose is None or any("white" not in pose.uv.get(c, {}) for c in cameras):
            raise CalibrationInputError(f"target {t}: the white circle was not seen in every camera")
        return [pose.uv[c]["white"] for c in cameras]

    def loop_poses(self, t: int, loop: str, use_survey: bool) -> list[SampledPose]:
        chosen = [p for p in self.poses if p.target == t and (p.phase == "approach" or
                                                               (p.phase == "iterate" and p.loop == loop))]
        if use_survey:
            chosen += [p for p in self.poses if p.phase == "survey" and p.target != t]
        return chosen

    def last_joints(self, t: int, loop: str) -> np.ndarray:
        own = [p for p in self.poses if p.target == t and p.phase == "iterate" and p.loop == loop]
        own = own or [p for p in self.poses if p.target == t and p.phase == "approach"]
        if not own:
            raise CalibrationInputError(f"target {t}: no approach samples")
        return max(own, key=lambda p: p.step).joints

    def centre(self, cam: str) -> np.ndarray:
        for p in self.poses:
            if cam in p.size:
                w, h = p.size[cam]
                return np.array([(w - 1) / 2, (h - 1) / 2])
        # offline files without the image size: the middle of the marks seen
        uv = np.array([v for p in self.poses for v in p.uv.get(cam, {}).values()])
        return (uv.min(axis=0) + uv.max(axis=0)) / 2


def camera_samples(data: SampleSet, poses: list[SampledPose], mode: str, cameras, kin: Kinematics,
                   distance_m: float) -> list[csm.CameraSamples]:
    """Per camera, (nominal 3D, camera-space) samples of the poses seen by every camera; `distance_m`: the
    roughly anticipated camera distance Z_r (eq. 9)."""
    names = {"white": ("white",), "three": BLACKS, "virtual": BLACKS}[mode]
    usable = [p for p in poses if all(all(n in p.uv.get(c, {}) for n in names) for c in cameras)]
    if not usable:
        raise CalibrationInputError(f"no pose with the {mode} feature(s) seen in every camera")
    points = np.array([kin.points(p.joints, names) for p in usable])  # (n, f, 3)
    out = []
    for c in cameras:
        uv = np.array([[p.uv[c][n] for n in names] for p in usable])
        if mode == "virtual":
            P, U = points.mean(axis=1), uv.mean(axis=1)
        else:
            P, U = points.reshape(-1, 3), uv.reshape(-1, 2)
        out.append(csm.CameraSamples(P, U, data.centre(c), distance_m))
    return out


def locate(data: SampleSet, poses: list[SampledPose], target_uv, mode: str, scheme: str, k: float, params,
           kin: Kinematics, fit_depth: bool | None = None) -> csm.Estimate:
    """The target's 3D position (eq. 10) from the view parameters of `poses` (csm-positioning's `params`:
    cameras, distance_mm, fit_depth unless given)."""
    cams = camera_samples(data, poses, mode, params.cameras, kin, params.distance_mm * 1e-3)
    fit_depth = params.fit_depth if fit_depth is None else fit_depth
    fit_depth = fit_depth and len(cams[0].points) >= 10  # Z_r needs samples spread in depth
    return csm.estimate(cams, target_uv, scheme, k, fit_depth=fit_depth)
