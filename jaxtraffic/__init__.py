"""jaxtraffic: JAX simulation and control of congested mixed ACC/manual freeway traffic.

Layers (imports flow one way, io/platform <- model <- control <- sim <- learn <- runs <- ecosystem, paper <- cli;
``tests/test_architecture.py`` enforces it):
    io/        atomic files and JSON, figures without pyplot, provenance
    platform/  devices, multi-process runs, the compilation cache, tracing
    model/     parameters, fundamental diagram, ARZ solver, delay buffer, linearisation
    control/   controller interface, baselines, three-gain law, learned gain policy, stability certificate
    sim/       plant state and the one closed-loop step, rollouts, initial conditions, metrics
    learn/     the algorithms: environment, PPO (ppo/), gradient-based and CEM training (gradient/)
    runs/      the lab: run directory, training loop, checkpoints, trainers, selection, load_policy
    ecosystem/ Gymnasium, gymnax and Stable-Baselines3 adapters
    paper/     the paper's scenarios, summaries, claims, report and figures
    cli/       the train and evaluate command lines

Gymnasium: when gymnasium is installed, ``import jaxtraffic`` registers ``"jaxtraffic/Gain-v0"``
(``jaxtraffic._registration``; the environment module is imported only by ``gymnasium.make``); so
does ``gymnax.make`` once gymnax is imported (before ``import jaxtraffic``, or
``import jaxtraffic.ecosystem.gymnax_env`` after it).

Devices: the batched entry points shard their batch over ``jax.devices()``. XLA shows a CPU host as
one device; ``split_host_devices()``, called before any JAX computation, makes it one device per core
(the command lines do this; ``import jaxtraffic`` changes nothing in your process; see
``jaxtraffic.platform.devices``).

Public API (the module map: docs/api/index.md):
    TrafficParams, equilibrium                      -- parameters and equilibrium
    simulate, simulate_batch, stack_params          -- jit-compiled, vmappable rollouts
    Record, Memory, AlphaInput                      -- rollout options (recording, checkpointing, plant alphas)
    Divergence, check_outcome                       -- outcome codes and the check that raises on divergence
    plant_alphas                                    -- the plant alphas a rollout draws (AlphaInput(alphas=...))
    paper_initial_condition, equilibrium_state      -- initial conditions
    open_loop, lyapunov, backstepping, constant_gains, Controller, Observation -- controllers
"""

from jaxtraffic._registration import register_gymnasium, register_gymnax
from jaxtraffic._version import __version__
from jaxtraffic.control import (
    Controller,
    Observation,
    backstepping,
    constant_gains,
    gain_law,
    lyapunov,
    open_loop,
    saturate,
)
from jaxtraffic.model.params import TrafficParams, cfl_number, equilibrium, steps_for
from jaxtraffic.platform.devices import split_host_devices
from jaxtraffic.sim import (
    AlphaInput,
    Divergence,
    Memory,
    Record,
    SimResult,
    Trajectory,
    check_outcome,
    equilibrium_state,
    paper_initial_condition,
    plant_alphas,
    simulate,
    simulate_batch,
    stack_params,
)

register_gymnasium()  # gymnasium.make("jaxtraffic/Gain-v0") when gymnasium is installed (_registration)
register_gymnax()  # gymnax.make("jaxtraffic/Gain-v0"), gymnax imported before or after (never imports it)

__all__ = [
    "__version__", "AlphaInput", "Controller", "Divergence", "Memory", "Observation", "Record", "SimResult",
    "TrafficParams", "Trajectory", "backstepping",
    "cfl_number", "check_outcome", "constant_gains", "equilibrium", "equilibrium_state", "gain_law", "lyapunov",
    "open_loop", "paper_initial_condition", "plant_alphas", "saturate", "simulate", "simulate_batch",
    "split_host_devices", "stack_params", "steps_for",
]
