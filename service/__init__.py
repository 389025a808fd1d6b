"""swarmvo service: the odometry behind a FastAPI REST + WebSocket API."""
