"""Layer 5: operator tools: the `splittag` CLI, the launcher and monitor, link emulation, link probing,
offline detection.
"""
