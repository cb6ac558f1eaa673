"""Layer 3: training data generation (synthetic and rendered), shards and contact sheets."""
