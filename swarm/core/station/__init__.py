"""The ground station's pure core: agents, alerts, commands and their delivery, swarms, plans, deltas
and federation.
"""
