"""The radio bridge's pure decisions: air-time queues, the name table, and which RADIO_STATUS reports
are ours.
"""
