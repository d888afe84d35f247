"""symcal: autonomous calibration through sensor redundancy, built on CasADi.

The public API follows the one-way flow of DESIGN.md::

    problem = symcal.load_problem("problems/platen_self_calibration.yaml")
    result = symcal.solve(problem)                       # datasets from the problem file
    result = symcal.solve(problem, {"calibration": "run.csv"})
    print(result.report()); result.params["s1.k1"]; result.to_dict()
"""

from symcal.calibrate import load_datasets, solve
from symcal.data import Dataset, read_table
from symcal.errors import DataError, SolveError, SpecError, SymcalError
from symcal.problem import Problem, load_problem
from symcal.result import Result

__all__ = [
    "DataError", "Dataset", "Problem", "Result", "SolveError", "SpecError", "SymcalError",
    "load_datasets", "load_problem", "read_table", "solve",
]
__version__ = "0.1.0"
