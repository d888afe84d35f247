"""Acceptance systems and harness of issue 23: symcal run as a user runs it.

``cases.yaml`` lists the cases (a problem, a scenario with or without a hidden effect,
the honest ending, the hidden effect's own term); ``harness.py`` runs each one through
the command line (simulate, solve, diagnose and its printed suggestion, improve and its
final problem) for several seeds and tabulates the outcome; ``benchmarks/acceptance.py``
is the runner.  The folders hold the systems that are not the courier (a thermistor bath,
a tumbled magnetometer) and the scenario overlays that switch hidden effects on.
"""
