"""The leader election and swarm membership: the paper's protocol, its rules, liveness, the size cap
and the tdm variant.
"""
