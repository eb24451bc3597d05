"""The radio bridge: the swarm's Zenoh key space carried over a SiK radio, both directions."""
