"""Layer 2: marker SLAM (GTSAM iSAM2) and trajectory files."""
