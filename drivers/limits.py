"""Limits every arm driver enforces before it moves: a workspace box in the robot frame."""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers.interfaces import MotionRejected, Pose


class WorkspaceBox(BaseModel):
    """Targets outside this box are refused before anything moves (edges in mm and degrees)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    x_mm: tuple[float, float] = Field(..., description="(min, max)")
    y_mm: tuple[float, float] = Field(...)
    z_mm: tuple[float, float] = Field(...)
    alpha_deg: tuple[float, float] = Field((-180.0, 180.0))

    @model_validator(mode="after")
    def _ordered(self):
        for name in ("x_mm", "y_mm", "z_mm", "alpha_deg"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ValueError(f"limits.{name}: min {lo} must be below max {hi}")
        return self

    def check(self, target: Pose) -> None:
        values = {
            "x_mm": target.x * 1e3,
            "y_mm": target.y * 1e3,
            "z_mm": target.z * 1e3,
            "alpha_deg": math.degrees(target.alpha),
        }
        for name, value in values.items():
            lo, hi = getattr(self, name)
            if not math.isfinite(value):
                raise MotionRejected(f"target {name}={value} is not a finite number; nothing moved")
            if not lo <= value <= hi:
                raise MotionRejected(
                    f"target {name}={value:.4f} is outside the workspace box [{lo}, {hi}]; nothing moved"
                )
