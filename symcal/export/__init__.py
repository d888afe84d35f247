"""Code generation: the calibrated model as C.

The flow, one way: :mod:`~symcal.export.plan` decides what an export holds as plain data
(names, declared units, values; results read through ``Result.load`` by
:mod:`~symcal.export.baked`), :mod:`~symcal.export.casadi_code` has CasADi write the
functions of one observation, and the Jinja2 templates of a target
(:mod:`~symcal.export.render`, ``templates/<target>/``) write the code around them;
:func:`symcal.export.c.generate` writes the files.
"""
