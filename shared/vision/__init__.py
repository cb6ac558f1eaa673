"""Layer 0: the camera model, geometry and conventions, the AprilTag detector, PnP, tag rendering and
metrics, the tag-map format.
"""
