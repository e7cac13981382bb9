"""Real camera drivers: GenICam through harvesters, UVC through OpenCV, OAK through depthai."""
