"""The ground control station (the paper, section 3; DESIGN.md section 9).

* :mod:`swarm.gcs.station`: the station side of the connection protocol
  (:mod:`swarm.gslink` is the agent side) as a pure core, :class:`StationCore`, and
  its threaded runtime over Zenoh or a radio, :class:`Station`.
* :mod:`swarm.gcs.server`: the HTTP + WebSocket server (JSON API and the web page).
* :mod:`swarm.gcs.replay`: a captured flight (``.tlog``) played into the same core.
"""
