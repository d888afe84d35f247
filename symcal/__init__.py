"""symcal: autonomous calibration through sensor redundancy, built on CasADi.

The public API follows the one-way flow of ARCHITECTURE.md::

    problem = symcal.load_problem("problems/platen_self_calibration.yaml")
    result = symcal.solve(problem)                       # datasets from the problem file
    result = symcal.solve(problem, {"calibration": "run.csv"},
                          symcal.SolveOptions(method="ipopt", max_iter=50))
    print(symcal.text_report(result)); result.params["s1.k1"]; result.to_dict()
    result.save("out/result.json"); symcal.Result.load("out/result.json")
"""

from typing import TYPE_CHECKING as _TYPE_CHECKING

# BLAS threads: symcal's linear algebra is on tall, skinny matrices, where OpenBLAS's
# threads cost more than they give (on 2 cores: 1.6x to 60x slower, benchmarks/RESULTS.md).
# symcal holds BLAS to one thread (or the user's OPENBLAS_NUM_THREADS) around its own
# passes and solver steps only, through threadpoolctl, whatever was imported first
# (symcal.solvers.executor.blas_limit); nothing is set at import, so a program's own
# numpy keeps its threads.
from symcal.base.errors import DataError, SolveError, SpecError, SymcalError

# The rest of the API is imported on first use (PEP 562), so that ``import symcal.cli``
# (``symcal --help``) does not load CasADi, SciPy, pint or Dask.
_LAZY = {
    "solve": "symcal.calibrate.solve", "Dataset": "symcal.data.dataset",
    "read_table": "symcal.data.dataset",
    "load_datasets": "symcal.data.loading", "FleetResult": "symcal.calibrate.fleet",
    "solve_fleet": "symcal.calibrate.fleet", "SolveOptions": "symcal.language.options",
    "Problem": "symcal.problem.compiler", "load_problem": "symcal.problem.compiler",
    "text_report": "symcal.report.text", "Result": "symcal.calibrate.result",
    "solve_partitioned": "symcal.calibrate.partitioned", "open_shards": "symcal.data.shards",
}

if _TYPE_CHECKING:
    from symcal.calibrate.fleet import FleetResult, solve_fleet
    from symcal.calibrate.partitioned import solve_partitioned
    from symcal.calibrate.result import Result
    from symcal.calibrate.solve import solve
    from symcal.data.dataset import Dataset, read_table
    from symcal.data.loading import load_datasets
    from symcal.data.shards import open_shards
    from symcal.language.options import SolveOptions
    from symcal.problem.compiler import Problem, load_problem
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
