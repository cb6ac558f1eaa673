"""Layer 3: the per-frame cores that combine the layers below: one image to tag poses, and the
robot/edge split steps.
"""
