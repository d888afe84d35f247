"""symcal: autonomous calibration through sensor redundancy, built on CasADi.

The public API follows the one-way flow of DESIGN.md::

    problem = symcal.load_problem("problems/platen_self_calibration.yaml")
    result = symcal.solve(problem)                       # datasets from the problem file
    result = symcal.solve(problem, {"calibration": "run.csv"})
    print(result.report()); result.params["s1.k1"]; result.to_dict()
"""

import os as _os
import sys as _sys

# symcal's linear algebra is on tall, skinny matrices, where OpenBLAS's threads cost more
# than they give (measured on 2 cores: up to 25x slower, benchmarks/RESULTS.md).  Unless
# the user chose otherwise, use one BLAS thread; this only takes effect if numpy has not
# been imported yet.
if "numpy" not in _sys.modules:
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        _os.environ.setdefault(_var, "1")

from symcal.calibrate import load_datasets, solve  # noqa: E402
from symcal.data import Dataset, read_table  # noqa: E402
from symcal.errors import DataError, SolveError, SpecError, SymcalError  # noqa: E402
from symcal.problem import Problem, load_problem  # noqa: E402
from symcal.result import Result  # noqa: E402

__all__ = [
    "DataError", "Dataset", "Problem", "Result", "SolveError", "SpecError", "SymcalError",
    "load_datasets", "load_problem", "read_table", "solve",
]
__version__ = "0.1.0"
