"""Real camera drivers: GenICam through harvesters or Aravis, UVC through OpenCV, OAK through depthai."""
