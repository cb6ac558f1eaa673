"""Layer 2: Rerun recordings."""
