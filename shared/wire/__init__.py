"""Layer 1: what travels between processes: the msgpack codec, versioned message schemas, key
expressions, the cut table.
"""
