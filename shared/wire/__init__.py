"""Layer 1: what travels between processes: the codec (msgpack header, tensors out of band), versioned
message schemas, key expressions, the cut table.
"""
