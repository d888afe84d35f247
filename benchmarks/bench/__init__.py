"""symcal's benchmark harness, one module per concern; ``benchmarks/run.py`` runs it.

* :mod:`bench.cli`: options, the order of the jobs, the console output, RESULTS.md.
* :mod:`bench.config`: the problems, the methods, the run's settings and shared state.
* :mod:`bench.children`: running one job in a fresh interpreter, and its child side.
* :mod:`bench.measure`: clocks and memory (peak and current resident set size).
* :mod:`bench.problems`: data files, the numpy residuals, the single-stage problems.
* :mod:`bench.peers`: what a user would write instead of symcal (numpy and scipy).
* :mod:`bench.jobs`: the seven jobs, each with its child side and its parent side.
* :mod:`bench.analysis`, :mod:`bench.report`, :mod:`bench.why`, :mod:`bench.fmt`: fitted
  exponents and targets, the Markdown of RESULTS.md, and number formatting.
"""
