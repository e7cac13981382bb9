"""Real vacuum gripper drivers over Modbus: Robotiq EPick (RTU) and OnRobot VGC10 (TCP)."""
