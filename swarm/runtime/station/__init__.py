"""The ground station's runtime: the live and replayed stations, their fleet view, the HTTP and
WebSocket server and its page.
"""
