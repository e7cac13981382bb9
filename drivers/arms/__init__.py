"""Real arm drivers: ABB over the open_abb socket protocol, Universal Robots over RTDE."""
