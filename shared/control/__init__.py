"""Layer 2: the adaptive split: link model and online estimator, compute estimates C(k)/E(k), the
controller's pure core.
"""
