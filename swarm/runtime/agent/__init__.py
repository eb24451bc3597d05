"""The agent's runtime: its pure node driven in real time over Zenoh (and a radio), and its flight
controller read in swarm terms.
"""
