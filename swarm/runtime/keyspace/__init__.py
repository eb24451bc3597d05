"""The swarm's key space on Zenoh: sessions, mutual TLS, certificates and the router's own log."""
