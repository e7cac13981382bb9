"""What the VR routines share (seed 000): the nominal layout, the operator's extra verbs, one stop's
measurement (capture, clicks, lines), the matching pipelines and overlays (the sample rows: _samples.py).

Frames: the world is the robot base frame. The ORU's nominal pose is the arm's
reported tool pose (the ORU sits at the tool frame, nominally); the simultaneous
update keeps it fixed (eq. 46: one frame must be fixed), so errors of the grasp and
of the arm go into the camera estimates, and what the cell needs, the ORU relative
to the receptacle, comes out right. "Alignment" below is the ORU's pose in the
receptacle frame, A = M_rec^-1 M_oru (as in the seed: the ORU's alignment pose
relative to the receptacle); its error is given in the receptacle frame (position
of the ORU's origin, rotation), and its predicted covariance follows from that of
the receptacle's incremental variables (`alignment_sigma`).

Operator protocol extension (`VrOperator`): the Operator of drivers/interfaces.py
plus three verbs, which the simulated operator performs in the world and the web
operator (`backend: web`, drivers/operators/web.py) asks of a person at the console:

- `click_points(camera, frame, obj, model_points, at_least, projected=None, edges=None)
  -> [(index, u, v)]`: the operator clicks a model point on the overlay, then its image
  point (seed Fig. 6); `model_points` are the object's model vertices (object frame,
  m), `projected` the same points in `frame`'s pixels under the current estimate and
  `edges` the model's index pairs (what the overlay draws for the operator to pick
  from; a simulated operator needs neither); the reply names which ones were clicked
  and where in `frame`; [] if fewer than `at_least` are visible;
- `align_by_hand(arm, standoff_m)`: the operator jogs the arm until the ORU stands
  aligned `standoff_m` in front of the receptacle (the seed's reference alignment,
  section VII); the routine then reads the arm pose;
- `mount_camera(camera, inter_camera_angle_deg=None, view_width_in=None, look_at_in=None)`:
  re-mount, zoom or aim a camera for an experiment's viewing condition (None: as
  in the cell's nominal layout). Idempotent: nothing happens when the camera is
  already mounted so (vr-experiments asks again before every measurement, so a
  resumed run measures with the cameras its plan says).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from geometry.orientation import quaternion_wxyz
from geometry.projection import focal_px, layout_view
from geometry.transforms import inverse, pose_matrix

from drivers.interfaces import Frame, Operator, Pose

from calibration.errors import CalibrationInputError
from calibration.models.edge_model import EdgeModel
from calibration.models.model_matching import (
    CameraState,
    MatchResult,
    ObjectState,
    Observations,
    solve,
    weighted_residuals,
)
from calibration.routines.base import Devices, Params
from calibration.vision.lines import EdgeImage, depth_buffer, detect_lines, edge_image, visible_segment_arrays

INCH = 0.0254
CAM, OBJ = ("side", "top"), ("oru", "receptacle")  # solver indices: cameras 0, 1; objects 0 (fixed), 1


@runtime_checkable
class VrOperator(Operator, Protocol):
    def click_points(self, camera: str, frame: Frame, obj: str, model_points, at_least: int = 5,
                     projected=None, edges=None) -> list: ...

    def align_by_hand(self, arm, standoff_m: float) -> None: ...

    def mount_camera(self, camera: str, inter_camera_angle_deg: float | None = None,
                     view_width_in: float | None = None, look_at_in=None) -> None: ...


class VrCameraNominal(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    device: str = Field(..., description="camera name in the cell file")
    distance_m: float = Field(..., gt=0.2, le=50)
    vfov_deg: float = Field(..., gt=0.5, le=120)


class VrParams(Params):
    """The nominal layout (the engineer's rough knowledge) and the matching options."""

    oru_model: str = Field("models/oru.json", description="the ORU's edge model (JSON; a relative path not "
                           "found is read from config/)")
    receptacle_model: str = Field("models/receptacle.json", description="the receptacle's edge model")
    receptacle_in: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="the receptacle's nominal "
                                                      "position (x, y, z)")
    receptacle_yaw_deg: float = Field(0.0, description="its nominal turn about the vertical")
    look_at_in: tuple[float, float, float] = Field((0.0, 10.0, 0.0), description="where both cameras' nominal "
                                                   "views point (x, y, z)")
    side_azimuth_deg: float = Field(35.0, description="the side camera's nominal direction from that point: "
                                    "azimuth")
    side_elevation_deg: float = Field(15.0, description="the side camera's nominal direction: elevation")
    inter_camera_angle_deg: float = Field(50.0, gt=0, le=120, description="nominal angle between the two "
                                          "cameras' views")
    side: VrCameraNominal = Field(VrCameraNominal(device="side", distance_m=7.5, vfov_deg=5.3),
                                  description="the side camera: its device, distance and vertical field of view")
    top: VrCameraNominal = Field(VrCameraNominal(device="top", distance_m=3.5, vfov_deg=12.0),
                                 description="the overhead camera: the same")
    initial_offset_in: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description=
                                                          "added to the receptacle's initial (nominal) position")
    initial_turn_deg: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="rotation (x, y, z) "
                                                         "added to the receptacle's initial orientation")
    fit_focal: bool = Field(True, description="7 variables per camera; False: the focal lengths are known (6)")
    focal_prior_pct: float = Field(25.0, ge=0, le=100, description="1-sigma of the nominal focal lengths, a weak "
                                   "prior in the point-based coarse matching (0: none); long lenses need it with few points")
    focal_prior_in_fine: bool = Field(False, description="also use the focal-length prior in the line-based updates "
                                      "(the seed's 7 variables per camera have none)")
    click_sigma_px: float = Field(3.0, gt=0, le=50, description="assumed error of a clicked point")
    min_clicks: int = Field(5, ge=4, le=50, description="per object and view")
    search_px: int = Field(20, ge=3, le=100, description="line detector search half-width")
    segment_px: float = Field(20.0, ge=5, le=200, description="a visible model edge is searched in pieces this "
                              "long")
    sigma_sys_px: float = Field(0.5, ge=0, le=10, description="systematic error of a detected line (seed 000 "
                                "eqs. 10-11)")
    rounds: int = Field(2, ge=1, le=5, description="detect-then-solve rounds of a line-based update")
    gate: float = Field(4.0, gt=1, le=100, description="line measurements with sqrt(h^T w h) above this are dropped")
    max_rms_px: float = Field(3.0, gt=0, le=100, description="a line-based update with a larger RMS residual failed")
    max_move_in: float = Field(6.0, gt=0, le=100, description="a line-based update moving the alignment further "
                               "failed (the detector only searches search_px around the projection)")


def pose_of(T: np.ndarray) -> Pose:
    x, y, z = (float(v) for v in T[:3, 3])
    return Pose(x, y, z, orientation=quaternion_wxyz(Rotation.from_matrix(T[:3, :3])))


def translate(d_m: float) -> np.ndarray:
    return pose_matrix(translation=(0.0, d_m, 0.0))


def operator_of(devices: Devices, needed_by: str) -> VrOperator:
    op = devices.operator
    if not isinstance(op, VrOperator):
        raise CalibrationInputError(f"{needed_by} needs an operator who can click points (click_points), align by "
                                    f"hand and mount cameras: operator backend 'web' (a person at the daemon's web "
                                    f"console) or 'sim-vr' (simulated); a terminal ('console') cannot click")
    return op


def load_models(params: VrParams) -> dict[str, EdgeModel]:
    return {"oru": EdgeModel.load(params.oru_model), "receptacle": EdgeModel.load(params.receptacle_model)}


# ------------------------------------------------------------------ the estimate

@dataclass
class Estimate:
    cameras: list[CameraState]  # side, top
    oru: np.ndarray  # fixed: the arm's reported pose
    receptacle: np.ndarray

    def objects(self, receptacle_free: bool = True) -> list[ObjectState]:
        return [ObjectState(self.oru, free=False), ObjectState(self.receptacle, free=receptacle_free)]

    def alignment(self) -> np.ndarray:
        """The ORU in the receptacle frame."""
        return inverse(self.receptacle) @ self.oru

    def with_oru(self, oru: np.ndarray) -> Estimate:
        return Estimate(list(self.cameras), oru, self.receptacle)

    def to_dict(self) -> dict:
        """The form a `vr` calibration stores (4x4 matrices, m, px); a sample row holds it as columns (_samples.py)."""
        return {"cameras": [dict(c.to_dict(), f_prior=c.f_prior, f_prior_rel=c.f_prior_rel) for c in self.cameras],
                "oru": self.oru.tolist(),
                "receptacle": self.receptacle.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Estimate:
        cams = [CameraState.from_dict(c, f_prior=c.get("f_prior"), f_prior_rel=c.get("f_prior_rel", 0.1)) for c in d["cameras"]]
        return cls(cams, np.asarray(d["oru"]), np.asarray(d["receptacle"]))


def nominal_camera(params: VrParams, name: str, resolution, angle_deg=None, view_width_in=None,
                   look_at_in=None) -> CameraState:
    nom = params.side if name == "side" else params.top
    angle = params.inter_camera_angle_deg if angle_deg is None else angle_deg
    target = np.asarray(params.look_at_in if look_at_in is None else look_at_in) * INCH
    V = layout_view(target, nom.distance_m, params.side_azimuth_deg, params.side_elevation_deg,
                    angle if name == "top" else 0.0)
    width, height = resolution
    f = focal_px(width, height, nom.distance_m, nom.vfov_deg, view_width_in * INCH if view_width_in else None)
    return CameraState.centred(V, f, width, height, free_f=params.fit_focal,
                               f_prior=f if params.focal_prior_pct else None, f_prior_rel=params.focal_prior_pct / 100)


def initial_estimate(params: VrParams, devices: Devices, oru: np.ndarray, setup: dict | None = None) -> Estimate:
    setup = setup or {}
    cams = [nominal_camera(params, n, devices.camera(getattr(params, n).device).resolution,
                           setup.get("angle"), setup.get("view"), setup.get("look_at")) for n in CAM]
    rec = pose_matrix([0, 0, math.radians(params.receptacle_yaw_deg)], np.asarray(params.receptacle_in) * INCH)
    rec = rec @ pose_matrix(np.radians(params.initial_turn_deg), np.asarray(params.initial_offset_in) * INCH)
    return Estimate(cams, oru, rec)


# ------------------------------------------------------------------ measurements

def capture_both(params: VrParams, devices: Devices) -> list[Frame]:
    return [devices.camera(getattr(params, n).device).capture() for n in CAM]


def click_observations(params: VrParams, devices: Devices, frames: list[Frame], models,
                       est: Estimate | None = None) -> Observations:
    """Operator correspondences for both objects in both views (seed section VI, Fig. 6); with `est`, the
    operator is shown the model points where the estimate projects them, to pick from."""
    op = operator_of(devices, "coarse matching")
    parts = []
    for i, (name, frame) in enumerate(zip(CAM, frames)):
        for j, obj in enumerate(OBJ):
            shown = {}
            if est is not None:
                M = (est.oru, est.receptacle)[j]
                shown = {"projected": est.cameras[i].project(models[obj].vertices @ M[:3, :3].T + M[:3, 3]),
                         "edges": models[obj].edges}
            clicks = op.click_points(getattr(params, name).device, frame, obj, models[obj].vertices, params.min_clicks,
                                     **shown)
            if len(clicks) < params.min_clicks:
                raise CalibrationInputError(f"only {len(clicks)} points clicked for the {obj} in the {name} view; "
                                            f"at least {params.min_clicks} are needed")
            idx = np.array([c[0] for c in clicks], int)
            uv = np.array([[c[1], c[2]] for c in clicks], float)
            n = len(idx)
            W = np.repeat(np.eye(2)[None] / params.click_sigma_px**2, n, axis=0)
            parts.append(Observations(point_cam=np.full(n, i), point_obj=np.full(n, j), X=models[obj].vertices[idx],
                                      uv=uv, point_W=W))
    return Observations.concat(parts)


def line_observations(params: VrParams, frame: Frame, cam_index: int, est: Estimate, models,
                      objects=(0, 1), edges: EdgeImage | None = None) -> Observations:
    """Visible model segments of the chosen objects projected with the estimate, and the image lines beside them.

    `edges`: the frame's edge_image when the caller detects on the same frame more than once (it is then not
    computed again)."""
    if not len(objects):
        return Observations()
    cam = est.cameras[cam_index]
    poses = [est.oru, est.receptacle]
    height, width = frame.image.shape[:2]
    faces = []
    for j, obj in enumerate(OBJ):
        CM = cam.V @ poses[j]
        v = models[obj].vertices @ CM[:3, :3].T + CM[:3, 3]
        faces += [v[f] for f in models[obj].faces]
    zbuf = depth_buffer(width, height, faces, cam.f, cam.cu, cam.cv)
    # the chosen objects' edges, stacked: one visibility pass for all
    E, Ec, of = [], [], []
    for j in objects:
        m, CM = models[OBJ[j]], cam.V @ poses[j]
        E.append(m.vertices[m.edges])  # (n, 2, 3) object frame
        Ec.append(E[-1] @ CM[:3, :3].T + CM[:3, 3])  # camera frame
        of.append(np.full(len(m.edges), j))  # the object of each edge
    E, Ec, of = (np.concatenate(x) for x in (E, Ec, of))
    k, t0, t1 = visible_segment_arrays(zbuf, Ec[:, 0], Ec[:, 1], cam.f, cam.cu, cam.cv, params.segment_px)
    a, b, objs = E[k, 0], E[k, 1], of[k]
    P1, P2 = a + t0[:, None] * (b - a), a + t1[:, None] * (b - a)
    A, B = np.zeros((len(k), 2)), np.zeros((len(k), 2))
    for j in objects:
        sel = objs == j
        A[sel] = cam.project(P1[sel] @ poses[j][:3, :3].T + poses[j][:3, 3])
        B[sel] = cam.project(P2[sel] @ poses[j][:3, :3].T + poses[j][:3, 3])
    if not len(P1):
        return Observations()
    meas = detect_lines(frame.image if edges is None else edges, A, B, search_px=params.search_px,
                        sigma_sys=params.sigma_sys_px)
    ok = meas.ok
    n = int(ok.sum())
    return Observations(np.full(n, cam_index), objs[ok], P1[ok], P2[ok], meas.Q1[ok], meas.Q2[ok], meas.W[ok])


def edge_images(frames) -> list[EdgeImage]:
    """The frames made ready for line detection once, for the several detections a matching runs on them."""
    return [edge_image(f.image) for f in frames]


# ------------------------------------------------------------------ pipelines

def _cams(est: Estimate, free: tuple[bool, bool], fit_focal: bool, prior: bool = True) -> list[CameraState]:
    return [replace(c, free_pose=fr, free_f=fr and fit_focal, f_prior=c.f_prior if prior else None)
            for c, fr in zip(est.cameras, free)]


def point_coarse(params: VrParams, est: Estimate, obs: Observations) -> tuple[Estimate, dict[str, MatchResult]]:
    """Point-based sequential (camera calibrations on the ORU, receptacle from both views), then point-based
    simultaneous update: the seed's steps 4-5 of section VI."""
    results = {}
    cams = list(est.cameras)
    for i in range(2):
        r = solve(_cams(est, (i == 0, i == 1), params.fit_focal), est.objects(False),
                  obs.select(cams=[i], objs=[0]))
        cams[i] = r.cameras[i]
        results[f"camcal{i + 1}"] = r
    est = Estimate(cams, est.oru, est.receptacle)
    r = solve(_cams(est, (False, False), params.fit_focal), est.objects(True), obs.select(objs=[1]))
    est = Estimate(est.cameras, est.oru, r.objects[1].M)
    results["objloc12"] = r
    r = solve(_cams(est, (True, True), params.fit_focal), est.objects(True), obs)
    results["simultaneous"] = r
    return Estimate(r.cameras, est.oru, r.objects[1].M), results


class MatchFailed(RuntimeError):
    """Too few image lines were found next to the projected models to solve (the estimate is too far off)."""


def line_update(params: VrParams, frames, est: Estimate, models, free_cams: tuple[bool, bool], free_rec: bool,
                views=(0, 1), objects=(0, 1), edges: list[EdgeImage] | None = None) -> tuple[Estimate, MatchResult]:
    """Line-based update of the free blocks from the chosen views and objects, `rounds` times detect-then-solve.

    `edges`: the frames' edge_images if the caller has them (made here otherwise): every round detects on the
    same frames, only the projected models move."""
    result = None
    edges = edges or [edge_image(frames[i].image) if i in views else None for i in range(len(frames))]
    for _ in range(params.rounds):
        obs = Observations.concat([line_observations(params, frames[i], i, est, models, objects, edges[i])
                                   for i in views])
        start = (_cams(est, free_cams, params.fit_focal, params.focal_prior_in_fine), est.objects(free_rec))
        n_unknowns = sum(c.n_free() for c in start[0]) + sum(o.n_free() for o in start[1])
        if 2 * obs.n_lines < n_unknowns + 4:
            raise MatchFailed(f"{obs.n_lines} image lines found for {n_unknowns} unknowns (views {views}, objects "
                              f"{[OBJ[j] for j in objects]}): the estimate is too far off for the line detector")
        result = solve(*start, obs)
        # a line detected on the wrong edge (a parallel edge a few pixels away, a fold without contrast) stands
        # out after the fit: drop measurements beyond the gate and solve again from the same start, until the
        # kept set settles
        keep = np.ones(obs.n_lines, bool)
        for _ in range(4):
            new_keep = line_chi(result, obs) <= params.gate
            if np.array_equal(new_keep, keep) or 2 * new_keep.sum() < n_unknowns + 4:
                break
            keep = new_keep
            result = solve(*start, obs.select_lines(keep))
        obs = obs.select_lines(keep)
        new = Estimate(result.cameras, est.oru, result.objects[1].M)
        moved = np.linalg.norm(new.alignment()[:3, 3] - est.alignment()[:3, 3]) / INCH
        if not (np.isfinite(result.cost) and result.rms_px <= params.max_rms_px and moved <= params.max_move_in):
            raise MatchFailed(f"the update diverged (rms {result.rms_px:.3g} px, alignment moved {moved:.3g} in); "
                              "the estimate is too far off for the line detector")
        est = new
    return est, result


def line_chi(result: MatchResult, obs: Observations) -> np.ndarray:
    """sqrt(h^T w h) of each line measurement at the solution (all lines at once, no Jacobian)."""
    only = obs.select_lines(np.ones(obs.n_lines, bool))
    r, W = weighted_residuals(result.cameras, result.objects, only)
    return np.sqrt(np.einsum("ni,nij,nj->n", r, W, r))


def fine_methods(params: VrParams, frames, est: Estimate, models, methods) -> dict[str, tuple[Estimate, MatchResult]]:
    """Line-based methods of the seed's Fig. 7 from one starting estimate: the sequential update (camera
    calibrations on the ORU, then the receptacle from view 1, view 2 or both) and the simultaneous update."""
    out = {}
    edges = edge_images(frames)  # all methods detect on the same two frames
    if {"objloc1", "objloc2", "objloc12"} & set(methods):
        cal = est
        try:
            for i in range(2):
                cal, _ = line_update(params, frames, cal, models, (i == 0, i == 1), False, views=(i,), objects=(0,),
                                     edges=edges)
        except MatchFailed as exc:
            cal = exc
        for name, views in (("objloc1", (0,)), ("objloc2", (1,)), ("objloc12", (0, 1))):
            if name in methods:
                out[name] = _attempt(lambda v=views: line_update(params, frames, cal, models, (False, False), True,
                                                                 views=v, objects=(1,), edges=edges), cal)
    if "simultaneous" in methods:
        out["simultaneous"] = _attempt(lambda: line_update(params, frames, est, models, (True, True), True,
                                                           edges=edges))
    return out


def _attempt(update, before=None):
    """(estimate, result) of an update, or the MatchFailed that stopped it (or an earlier stage)."""
    if isinstance(before, MatchFailed):
        return before
    try:
        return update()
    except MatchFailed as exc:
        return exc


# ------------------------------------------------------------------ alignment errors

def alignment_error(est_alignment: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(dx, dy, dz, rx, ry, rz) of the estimated ORU-in-receptacle pose against a reference, receptacle frame:
    the ORU origin's position error and the rotation error."""
    dR = est_alignment[:3, :3] @ reference[:3, :3].T
    return np.concatenate([est_alignment[:3, 3] - reference[:3, 3], Rotation.from_matrix(dR).as_rotvec()])


def error_summary(e: np.ndarray) -> tuple[float, float]:
    """Position error (in) and orientation error (deg): vector sums over the three axes, as in the seed."""
    return float(np.linalg.norm(e[:3]) / INCH), float(np.degrees(np.linalg.norm(e[3:])))


def alignment_sigma(result: MatchResult, est: Estimate) -> np.ndarray:
    """Predicted 1-sigma of the alignment error components (m, rad), from the covariance of the receptacle's
    incremental variables: a receptacle update (v, w) moves the ORU's origin t (receptacle frame) by
    -v + [t]x w and turns the alignment by -w."""
    t = est.alignment()[:3, 3]
    J = np.zeros((6, 6))
    J[:3, :3] = -np.eye(3)
    J[:3, 3:] = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    J[3:, 3:] = -np.eye(3)
    return np.sqrt(np.maximum(np.diag(J @ result.block("obj1") @ J.T), 0.0))


# ------------------------------------------------------------------ overlays (seed Figs. 2-5)

COLOURS = {"oru": (80, 220, 80), "receptacle": (255, 80, 255)}


def overlay(frames: list[Frame], est: Estimate, models, title: str) -> np.ndarray:
    """The two views, side above overhead, with the estimated models' edges drawn over the video."""
    panels = []
    poses = {"oru": est.oru, "receptacle": est.receptacle}
    for i, frame in enumerate(frames):
        img = frame.image if frame.image.ndim == 3 else cv2.cvtColor(frame.image, cv2.COLOR_GRAY2BGR)
        img = img.copy()
        cam = est.cameras[i]
        for obj, m in models.items():
            X = m.vertices @ poses[obj][:3, :3].T + poses[obj][:3, 3]
            uv = cam.project(X)
            for a, b in m.edges:
                cv2.line(img, tuple(np.round(uv[a] * 16).astype(int)), tuple(np.round(uv[b] * 16).astype(int)),
                         COLOURS[obj], 1, cv2.LINE_AA, shift=4)
        cv2.putText(img, f"{title} - {CAM[i]}", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
        panels.append(img)
    return np.vstack(panels)


def overlay_frame(frames: list[Frame], est: Estimate, models, title: str, name: str) -> Frame:
    """`overlay` as a frame, kept in the run folder as images/stepNNNNN_overlay-NAME.png, at the views' time."""
    return Frame(overlay(frames, est, models, title), f"overlay-{name}", 0, None, frames[1].host_timestamp_s)
