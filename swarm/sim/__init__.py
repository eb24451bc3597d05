"""Virtual time: the election simulator, the flight simulator, tracks from captures."""
