"""Identification of the actuator's plant parameters from recorded runs.

``data`` (experiments from bags or traces), ``segments``, ``kernel``
(compiled short-horizon predictions), ``equation_error`` (the start),
``fit`` (least squares, intervals, identifiability: :func:`identify`),
``validate`` (closed-loop fit on a held-out run), ``params_out`` (the
params file), ``run`` (bags in, files out: :func:`identify_bags`).
"""
from has_control.identify.run import identify_bags  # noqa: F401
