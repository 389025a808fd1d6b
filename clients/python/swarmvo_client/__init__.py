"""Python client for the swarmvo odometry service."""
