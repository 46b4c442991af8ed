"""The simulation layer (imports ``model`` and ``control``): the plant state and the one
closed-loop step, rollouts (``simulate``, ``simulate_batch``) and their options (``Record``,
``Memory``, ``AlphaInput``), outcomes (``Divergence``, ``check_outcome``), initial conditions, metrics."""

from jaxtraffic.sim.initial import equilibrium_state, paper_initial_condition
from jaxtraffic.sim.options import AlphaInput, Memory, Record
from jaxtraffic.sim.outcome import DivergedError, Divergence, check_outcome
from jaxtraffic.sim.plant import NoiseReading, PlantState, StepInfo, closed_loop_step, initial_state, plant_step
from jaxtraffic.sim.rollout import SimResult, Trajectory, plant_alphas, simulate, simulate_batch, stack_params

__all__ = ["AlphaInput", "DivergedError", "Divergence", "Memory", "NoiseReading", "PlantState", "Record", "SimResult",
           "StepInfo", "Trajectory", "check_outcome", "closed_loop_step", "equilibrium_state", "initial_state",
           "paper_initial_condition", "plant_alphas", "plant_step", "simulate", "simulate_batch", "stack_params"]
