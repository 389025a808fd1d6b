"""Generated data with exact ground truth: point sets, rendered flights and drives, IMU
scenarios, and perturbed recordings."""
