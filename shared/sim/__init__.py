"""Layer 2: simulated worlds: the MuJoCo demo scene and procedural backgrounds."""
