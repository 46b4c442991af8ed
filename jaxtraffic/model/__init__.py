"""The physics layer: parameters and equilibrium, fundamental diagram, ARZ solver, input-delay
buffer, linearisation. Pure functions of arrays and ``TrafficParams``; imports nothing above it."""

from jaxtraffic.model.params import TrafficParams, cfl_number, equilibrium, steps_for

__all__ = ["TrafficParams", "cfl_number", "equilibrium", "steps_for"]
