"""The swarm's messages on the wire: the compact codec, its types, and the TUNNEL payloads that carry
them.
"""
