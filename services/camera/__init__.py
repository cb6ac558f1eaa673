"""camera service: publishes Frame messages (and ground truth when known) at a configured rate."""
