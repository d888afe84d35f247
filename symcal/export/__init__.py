"""Code generation: the calibrated model as C."""
