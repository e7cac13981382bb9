"""A six-axis arm: hand-eye (a camera on the wrist or over the table), the arm's own kinematics, and the ISO 9283
pose test that proves them. Each routine is one file here."""

from calibration.routines.sequence import Item, Sequence

SEQUENCES = (
    # the arm's acceptance: its ISO 9283 figures as it came, then calibrated, then again through the calibration
    # (the second hand-eye version, which arm-kinematics stores, is the camera the second test measures with)
    Sequence.of("arm-acceptance", "hand-eye", Item("iso9283.before", "iso9283"), "arm-kinematics",
                Item("iso9283.after", "iso9283"),
                description="ISO 9283 pose accuracy and repeatability before and after arm-kinematics"),
    # the same on a cell whose fixed cameras arm-kinematics calibrates (the IRB 120's): they measure both tests, the
    # first with the arm as its controller moves it, the second through the calibration
    Sequence.of("arm-acceptance-stereo", "arm-kinematics", Item("iso9283.before", "iso9283", {"moves": "controller"}),
                Item("iso9283.after", "iso9283"),
                description="arm-kinematics by fixed cameras, then ISO 9283 measured by them: the arm as its "
                            "controller moves it and through the calibration"),
)
