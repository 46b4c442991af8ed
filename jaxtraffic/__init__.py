"""jaxtraffic: JAX simulation and control of congested mixed ACC/manual freeway traffic.

Public API (see README.md for a module map):
    TrafficParams, equilibrium                      -- parameters and equilibrium
    simulate, simulate_batch, stack_params          -- jit-compiled, vmappable rollouts
    paper_initial_condition, equilibrium_state      -- initial conditions
    open_loop, lyapunov, backstepping, constant_gains, Controller, Observation -- controllers
"""

from jaxtraffic.controllers import (
    Controller,
    Observation,
    backstepping,
    constant_gains,
    gain_law,
    lyapunov,
    open_loop,
    saturate,
)
from jaxtraffic.params import TrafficParams, cfl_number, equilibrium, steps_for
from jaxtraffic.rollout import (
    SimResult,
    Trajectory,
    equilibrium_state,
    paper_initial_condition,
    simulate,
    simulate_batch,
    stack_params,
)

__version__ = "0.1.0"

__all__ = [
    "Controller", "Observation", "SimResult", "TrafficParams", "Trajectory", "backstepping",
    "cfl_number", "constant_gains", "equilibrium", "equilibrium_state", "gain_law", "lyapunov",
    "open_loop", "paper_initial_condition", "saturate", "simulate", "simulate_batch",
    "stack_params", "steps_for",
]
