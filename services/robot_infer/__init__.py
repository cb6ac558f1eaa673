"""robot_infer service: stage 1 + the network up to cut k; publishes Features; owns the split queryable."""
