"""What a vehicle does: the V-formation geometry, the pilot and the geofence, as pure functions and
state machines.
"""
