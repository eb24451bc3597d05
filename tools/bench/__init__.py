"""The project's own benches: they measure the simulator and the product against what
only the checkout holds (recorded traces of real autopilots, the real SITL builds), so
they are not in the wheel. Run them from a checkout with ``python -m tools.bench AREA``
(``--json``, ``--quick``, ``--real``), as ``swarm bench`` runs the product's."""
