"""A six-axis arm: hand-eye (a camera on the wrist or over the table) and the arm's kinematics, proven by the
ISO 9283 pose test. Its routines come with the next issues; each is one file here."""
