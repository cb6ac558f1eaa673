"""Layer 4: training and evaluation of the network."""
