"""controller service: the adaptive split controller (its own process on the robot side)."""
