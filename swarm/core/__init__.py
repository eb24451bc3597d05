"""The pure cores: messages, the TUNNEL codec, protocol, formation, pilot, station link,
agent node and station core. No I/O, no threads, no clock (checked by import contracts)."""
