"""2D/3D body joint detections at the intensity frames (paper Sec. 3.2): a simulated CNN detector and a file reader."""
