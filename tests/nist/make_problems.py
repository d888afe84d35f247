"""Write the 27 NIST StRD nonlinear regression problems as symcal problem files.

Run from the repository (``.venv/bin/python tests/nist/make_problems.py [SOURCE_DIR]``;
default source ``../shared/reference/nist-strd``).  For each problem NAME it writes, next to
this script:

* ``NAME.csv``: the data, each cell copied verbatim from the reference file (so the
  doubles symcal reads are the ones NIST's text denotes);
* ``NAME.start1.yaml`` and ``NAME.start2.yaml``: the problem from each of NIST's two
  starting points (a parameter's nominal scale is symcal's default, the magnitude of its
  start value, so nothing of the certified answer enters the problem);
* ``certified.json``: starts, certified values and standard deviations, certified residual
  sum of squares, numbers of observations and parameters.

The model of each problem is written here by hand from the ``Model:`` line of its
reference file (NIST's ``exp[...]`` and ``arctan`` spelled in symcal's expression language).
They are plain regressions on data columns: a symcal problem with parameters, columns
and a constraint, and no sensor instance.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_SOURCE = HERE.parent.parent.parent / "shared" / "reference" / "nist-strd"

#: NIST's models as symcal expressions of the response's prediction (Nelson: of log y).
MODELS: dict[str, str] = {
    "Misra1a": "b1*(1 - exp(-b2*x))",
    "Chwirut2": "exp(-b1*x)/(b2 + b3*x)",
    "Chwirut1": "exp(-b1*x)/(b2 + b3*x)",
    "Lanczos3": "b1*exp(-b2*x) + b3*exp(-b4*x) + b5*exp(-b6*x)",
    "Gauss1": "b1*exp(-b2*x) + b3*exp(-(x - b4)**2/b5**2) + b6*exp(-(x - b7)**2/b8**2)",
    "Gauss2": "b1*exp(-b2*x) + b3*exp(-(x - b4)**2/b5**2) + b6*exp(-(x - b7)**2/b8**2)",
    "DanWood": "b1*x**b2",
    "Misra1b": "b1*(1 - (1 + b2*x/2)**(-2))",
    "Kirby2": "(b1 + b2*x + b3*x**2)/(1 + b4*x + b5*x**2)",
    "Hahn1": "(b1 + b2*x + b3*x**2 + b4*x**3)/(1 + b5*x + b6*x**2 + b7*x**3)",
    "Nelson": "b1 - b2*x1*exp(-b3*x2)",
    "MGH17": "b1 + b2*exp(-x*b4) + b3*exp(-x*b5)",
    "Lanczos1": "b1*exp(-b2*x) + b3*exp(-b4*x) + b5*exp(-b6*x)",
    "Lanczos2": "b1*exp(-b2*x) + b3*exp(-b4*x) + b5*exp(-b6*x)",
    "Gauss3": "b1*exp(-b2*x) + b3*exp(-(x - b4)**2/b5**2) + b6*exp(-(x - b7)**2/b8**2)",
    "Misra1c": "b1*(1 - (1 + 2*b2*x)**(-0.5))",
    "Misra1d": "b1*b2*x*((1 + b2*x)**(-1))",
    "Roszman1": "b1 - b2*x - atan(b3/(x - b4))/pi",
    "ENSO": ("b1 + b2*cos(2*pi*x/12) + b3*sin(2*pi*x/12) + b5*cos(2*pi*x/b4)"
             " + b6*sin(2*pi*x/b4) + b8*cos(2*pi*x/b7) + b9*sin(2*pi*x/b7)"),
    "MGH09": "b1*(x**2 + x*b2)/(x**2 + x*b3 + b4)",
    "Thurber": "(b1 + b2*x + b3*x**2 + b4*x**3)/(1 + b5*x + b6*x**2 + b7*x**3)",
    "BoxBOD": "b1*(1 - exp(-b2*x))",
    "Rat42": "b1/(1 + exp(b2 - b3*x))",
    "MGH10": "b1*exp(b2/(x + b3))",
    "Eckerle4": "(b1/b2)*exp(-0.5*((x - b3)/b2)**2)",
    "Rat43": "b1/((1 + exp(b2 - b3*x))**(1/b4))",
    "Bennett5": "b1*(b2 + x)**(-1/b3)",
}
#: The response as NIST states the model (only Nelson models a transform of y).
RESPONSE = {"Nelson": "log(y)"}

#: Trial steps allowed: Bennett5 from start 1 needs about 2000 (a long, flat valley).
MAX_ITER = 3000

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def parse(path: Path) -> dict:
    """Read one NIST StRD ``.dat`` file: starts, certified values, data (as text)."""
    lines = path.read_text().splitlines()
    header = "\n".join(lines[:30])
    found = re.search(r"Data\s+\(lines\s+(\d+)\s+to\s+(\d+)\)", header)
    if found is None:
        raise ValueError(f"{path}: no data line range in the header")
    first, last = int(found.group(1)), int(found.group(2))
    columns = lines[first - 2].split()[1:]
    rows = [line.split() for line in lines[first - 1:last]]
    params: list[dict] = []
    for line in lines:
        m = re.match(rf"\s*(b\d+)\s*=\s*({_NUMBER})\s+({_NUMBER})\s+({_NUMBER})\s+({_NUMBER})",
                     line)
        if m:
            params.append({"name": m.group(1), "start1": m.group(2), "start2": m.group(3),
                           "value": float(m.group(4)), "se": float(m.group(5))})
    rss = re.search(rf"Residual Sum of Squares:\s+({_NUMBER})", "\n".join(lines))
    level = re.search(r"(Lower|Average|Higher) Level of Difficulty", header)
    if rss is None or level is None or not params:
        raise ValueError(f"{path}: certified values not found")
    return {"columns": columns, "rows": rows, "params": params, "rss": float(rss.group(1)),
            "difficulty": level.group(1).lower()}


def problem_text(name: str, info: dict, start: str) -> str:
    """The YAML of problem ``name`` from NIST's start ``start`` ("start1" or "start2")."""
    response = RESPONSE.get(name, "y")
    out = [f"problem: nist_{name.lower()}_{start}",
           "doc: >",
           f"  NIST StRD nonlinear regression '{name}' ({info['difficulty']} difficulty) from",
           f"  NIST's {start[:-1]} {start[-1]}.  Generated by tests/nist/make_problems.py.",
           "columns:"]
    out += [f"  {c}: {{}}" for c in info["columns"]]
    out += ["parameters:"]
    out += [f"  {p['name']}: {{value: {p[start]}}}" for p in info["params"]]
    out += ["constraints:",
            f"  residual: {{expr: '{response} - ({MODELS[name]})'}}",
            "datasets:",
            f"  calibration: {{path: {name}.csv}}",
            "solver:",
            "  method: lm",
            f"  max_iter: {MAX_ITER}",
            ""]
    return "\n".join(out)


def main(argv: list[str]) -> int:
    """Write every problem's files next to this script; the source folder is argv[1]."""
    source = Path(argv[1]) if len(argv) > 1 else DEFAULT_SOURCE
    certified: dict[str, dict] = {}
    for name in sorted(MODELS):
        info = parse(source / f"{name}.dat")
        (HERE / f"{name}.csv").write_text(
            "\n".join([",".join(info["columns"])] + [",".join(r) for r in info["rows"]])
            + "\n")
        for start in ("start1", "start2"):
            (HERE / f"{name}.{start}.yaml").write_text(problem_text(name, info, start))
        certified[name] = {
            "difficulty": info["difficulty"], "n": len(info["rows"]),
            "parameters": [p["name"] for p in info["params"]],
            "start1": [float(p["start1"]) for p in info["params"]],
            "start2": [float(p["start2"]) for p in info["params"]],
            "values": [p["value"] for p in info["params"]],
            "se": [p["se"] for p in info["params"]],
            "rss": info["rss"],
        }
    (HERE / "certified.json").write_text(json.dumps(certified, indent=1) + "\n")
    print(f"wrote {len(certified)} problems to {HERE}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
