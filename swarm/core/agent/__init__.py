"""One agent as a pure state machine: the node that composes the election, the pilot and the ground-
station link.
"""
