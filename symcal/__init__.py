"""symcal: autonomous calibration through sensor redundancy, built on CasADi.

The whole product, by public name (imported on first use)::

    problem = symcal.load_problem("problems/platen_self_calibration.yaml")
    result = symcal.solve(problem)                       # datasets from the problem file
    result = symcal.solve(problem, {"calibration": "run.csv"},
                          symcal.SolveOptions(method="ipopt", max_iter=50))
    result.params["s1.k1"].value, result.params["s1.k1"].se
    print(symcal.text_report(result)); result.to_dict()
    result.save("out/result.json"); symcal.Result.load("out/result.json")

    diagnosis = symcal.diagnose(result)                  # where it fails, what is missing
    print(symcal.diagnosis_report(diagnosis))
    symcal.improve("problems/platen_self_calibration.yaml", "revisions")   # the loop
    symcal.compare([result, other])                      # the ladder of revisions
    symcal.design(problem, symcal.load_scenario("scenario.yaml"), criterion="D")
    symcal.export(problem, "firmware", result)          # C of the calibrated model
    symcal.simulate(symcal.load_scenario("scenario.yaml"), seed=1)
    symcal.solve_fleet(problem, "fleet"); symcal.solve_partitioned(problem, "shards")
    symcal.solve(problem, progress=print, bars=symcal.terminal_bars())  # any long call

In a notebook, a :class:`Result` and a :class:`Diagnosis` display their report.
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
# (``symcal --help``) does not load CasADi, SciPy, pint or Dask.  Name -> (module, name).
_LAZY = {
    "load_problem": ("symcal.problem.build", "load_problem"),
    "Problem": ("symcal.problem.symbolic", "Problem"),
    "SolveOptions": ("symcal.base.options", "SolveOptions"),
    "Dataset": ("symcal.data.dataset", "Dataset"),
    "read_table": ("symcal.data.dataset", "read_table"),
    "load_datasets": ("symcal.data.loading", "load_datasets"),
    "open_shards": ("symcal.data.shards", "open_shards"),
    "load_scenario": ("symcal.simulation", "load_scenario"),
    "simulate": ("symcal.simulation", "simulate"),
    "solve": ("symcal.calibrate.solve", "solve"),
    "Result": ("symcal.calibrate.result", "Result"),
    "solve_partitioned": ("symcal.calibrate.partitioned", "solve_partitioned"),
    "solve_fleet": ("symcal.calibrate.fleet", "solve_fleet"),
    "FleetResult": ("symcal.calibrate.fleet", "FleetResult"),
    "predict": ("symcal.experiment.predict", "predict"),
    "design": ("symcal.experiment.optimize", "design"),
    "diagnose": ("symcal.revise.diagnose", "diagnose"),
    "Diagnosis": ("symcal.revise.diagnose", "Diagnosis"),
    "improve": ("symcal.revise.improve", "improve"),
    "Improvement": ("symcal.revise.improve", "Improvement"),
    "compare": ("symcal.revise.ladder", "compare"),
    "codegen": ("symcal.export.c", "generate"),
    "text_report": ("symcal.report.text", "text_report"),
    "json_report": ("symcal.report.text", "json_report"),
    "diagnosis_report": ("symcal.report.text", "diagnosis_report"),
    "ladder_report": ("symcal.report.ladder", "ladder_report"),
    "terminal_bars": ("symcal.base.progress", "terminal_bars"),
}

if _TYPE_CHECKING:
    from symcal.base.options import SolveOptions
    from symcal.base.progress import terminal_bars
    from symcal.calibrate.fleet import FleetResult, solve_fleet
    from symcal.calibrate.partitioned import solve_partitioned
    from symcal.calibrate.result import Result
    from symcal.calibrate.solve import solve
    from symcal.data.dataset import Dataset, read_table
    from symcal.data.loading import load_datasets
    from symcal.data.shards import open_shards
    from symcal.experiment.optimize import design
    from symcal.experiment.predict import predict
    from symcal.export.c import generate as codegen
    from symcal.problem.build import load_problem
    from symcal.problem.symbolic import Problem
    from symcal.report.ladder import ladder_report
    from symcal.report.text import diagnosis_report, json_report, text_report
    from symcal.revise.diagnose import Diagnosis, diagnose
    from symcal.revise.improve import Improvement, improve
    from symcal.revise.ladder import compare
    from symcal.simulation import load_scenario, simulate


def __getattr__(name: str) -> object:
    entry = _LAZY.get(name)
    if entry is None:
        raise AttributeError(f"module 'symcal' has no attribute '{name}'")
    import importlib

    value = getattr(importlib.import_module(entry[0]), entry[1])
    # the presenters register how results display in a notebook (results import none)
    importlib.import_module("symcal.report.display").register()
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "DataError", "Dataset", "Diagnosis", "FleetResult", "Improvement", "Problem", "Result",
    "SolveError", "SolveOptions", "SpecError", "SymcalError", "codegen", "compare", "design",
    "diagnose", "diagnosis_report", "improve", "json_report", "ladder_report",
    "load_datasets", "load_problem", "load_scenario", "open_shards", "predict", "read_table",
    "simulate", "solve", "solve_fleet", "solve_partitioned", "terminal_bars", "text_report",
]
__version__ = "0.1.0"
