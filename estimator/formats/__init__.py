"""Files in and out: datasets, calibration, trajectories, ROS bags, odometry messages."""
