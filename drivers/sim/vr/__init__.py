"""The simulated VR-calibration cell of seed 000 (Kim, section V): a robot holding an ORU-like box in front of
its receptacle, watched by a side and an overhead camera with long lenses."""
