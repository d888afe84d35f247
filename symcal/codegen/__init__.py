"""Code generation: the calibrated model as C.

The flow, one way: :mod:`~symcal.codegen.plan` decides what an export holds as plain data
(names, declared units, values; results read through ``Result.load`` by
:mod:`~symcal.codegen.baked`), :mod:`~symcal.codegen.casadi_code` has CasADi write the
functions of one observation, and the Jinja2 templates of a target
(:mod:`~symcal.codegen.render`, ``templates/<target>/``) write the code around them;
:func:`symcal.codegen.c.generate` writes the files.
"""
