"""Data: datasets in memory, a problem's datasets from files, objects or simulation, and
logs kept as shards."""
