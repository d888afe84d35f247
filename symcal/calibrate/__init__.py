"""Calibration: solve a problem on its data (in memory, as shards, or a fleet) into a Result."""
