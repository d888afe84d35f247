"""symcal: autonomous calibration through sensor redundancy, built on CasADi.

The public API follows the one-way flow of ARCHITECTURE.md::

    problem = symcal.load_problem("problems/platen_self_calibration.yaml")
    result = symcal.solve(problem)                       # datasets from the problem file
    result = symcal.solve(problem, {"calibration": "run.csv"},
                          symcal.SolveOptions(method="ipopt", max_iter=50))
    print(symcal.text_report(result)); result.params["s1.k1"].value; result.to_dict()
    result.save("out/result.json"); symcal.Result.load("out/result.json")
"""

import os as _os
import sys as _sys
from typing import TYPE_CHECKING as _TYPE_CHECKING

# symcal's linear algebra is on tall, skinny matrices, where OpenBLAS's threads cost more
# than they give (measured on 2 cores: up to 25x slower, benchmarks/RESULTS.md).  Unless
# the user chose otherwise, use one BLAS thread; this only takes effect if numpy has not
# been imported yet.
if "numpy" not in _sys.modules:
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        _os.environ.setdefault(_var, "1")

from symcal.base.errors import DataError, SolveError, SpecError, SymcalError  # noqa: E402

# The rest of the API is imported on first use (PEP 562), so that ``import symcal.cli``
# (``symcal --help``) does not load CasADi, SciPy, pint or Dask.
_LAZY = {
    "solve": "symcal.calibrate.solve", "Dataset": "symcal.data.dataset",
    "read_table": "symcal.data.dataset",
    "load_datasets": "symcal.data.loading", "FleetResult": "symcal.calibrate.fleet",
    "solve_fleet": "symcal.calibrate.fleet", "SolveOptions": "symcal.base.options",
    "Problem": "symcal.problem.symbolic", "load_problem": "symcal.problem.build",
    "text_report": "symcal.report.text", "Result": "symcal.calibrate.result",
    "solve_partitioned": "symcal.calibrate.partitioned", "open_shards": "symcal.data.shards",
}

if _TYPE_CHECKING:
    from symcal.base.options import SolveOptions
    from symcal.calibrate.fleet import FleetResult, solve_fleet
    from symcal.calibrate.partitioned import solve_partitioned
    from symcal.calibrate.result import Result
    from symcal.calibrate.solve import solve
    from symcal.data.dataset import Dataset, read_table
    from symcal.data.loading import load_datasets
    from symcal.data.shards import open_shards
    from symcal.problem.build import load_problem
    from symcal.problem.symbolic import Problem
    from symcal.report.text import text_report


def __getattr__(name: str) -> object:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'symcal' has no attribute '{name}'")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "DataError", "Dataset", "FleetResult", "Problem", "Result", "SolveError", "SolveOptions",
    "SpecError", "SymcalError", "load_datasets", "load_problem", "open_shards",
    "read_table", "solve", "solve_fleet", "solve_partitioned", "text_report",
]
__version__ = "0.1.0"
