"""Layer 2: the split keypoint network, its one inference path, weights files and compute profiling
(torch lives here).
"""
