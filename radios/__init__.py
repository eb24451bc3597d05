"""Bytes over serial radios: MAVLink 2 framing, links chosen by URL, a SiK radio
network emulator, AT configuration, capture and replay. Knows nothing of swarms."""
