"""Swarm messages, transport, protocol, formation, agent runtime, GCS and the `swarm` command."""
