"""Benchmarks behind ``swarm bench <area> --json``: each prints one JSON object of
figures (ratios and counts where possible: these machines are noisy)."""
