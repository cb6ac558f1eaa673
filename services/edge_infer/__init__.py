"""edge_infer service: the network's tail for the announced k, keypoints to image, PnP; publishes TagPoses."""
