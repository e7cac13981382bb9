"""Does a calibration still hold? The calibration check (a verdict, the target that drifted, a touch-up; its
`_judge`) and the arm's repeatability."""
