"""The swarm's Zenoh key space over IP: access control, what endpoints expose, what a router refused."""
