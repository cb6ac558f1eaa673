"""Layer 2: Zenoh plumbing: sessions, publishers and subscribers, flow control, link probes, the split
queryable and client.
"""
