"""Experiment design: predicted uncertainty of a motion and an optimised motion."""
