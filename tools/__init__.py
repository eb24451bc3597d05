"""The project's own tools, run from a checkout (never in the wheel)."""
