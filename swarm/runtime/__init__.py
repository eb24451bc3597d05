"""The runtimes: Zenoh transport, radio bridge, the agent and station threads, the HTTP server."""
