"""symcal: autonomous calibration through sensor redundancy, built on CasADi.

The public API follows the one-way flow of ARCHITECTURE.md::

    problem = symcal.load_problem("problems/platen_self_calibration.yaml")
    result = symcal.solve(problem)                       # datasets from the problem file
    result = symcal.solve(problem, {"calibration": "run.csv"},
                          symcal.SolveOptions(method="ipopt", max_iter=50))
    print(symcal.text_report(result)); result.params["s1.k1"]; result.to_dict()
    result.save("out/result.json"); symcal.Result.load("out/result.json")
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

from symcal.calibrate import solve  # noqa: E402
from symcal.data import Dataset, read_table  # noqa: E402
from symcal.datasets import load_datasets  # noqa: E402
from symcal.errors import DataError, SolveError, SpecError, SymcalError  # noqa: E402
from symcal.language.options import SolveOptions  # noqa: E402
from symcal.problem import Problem, load_problem  # noqa: E402
from symcal.report import text_report  # noqa: E402
from symcal.result import Result  # noqa: E402

__all__ = [
    "DataError", "Dataset", "Problem", "Result", "SolveError", "SolveOptions", "SpecError",
    "SymcalError", "load_datasets", "load_problem", "read_table", "solve", "text_report",
]
__version__ = "0.1.0"
