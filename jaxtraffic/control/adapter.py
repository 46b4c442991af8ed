"""A controller designed on one discretisation acting on a plant of another (docs/model.md section 15).

A controller is built (or trained) on a *controller grid*: ``n_points`` nodes on the road and a
control period ``dt`` (its nominal ``TrafficParams``). ``adapt(controller, grid, plant)`` returns
the same controller acting on ``plant``'s grid, whose spacing and time step divide the
controller's by integers r = dx_ctrl / dx_plant and s = dt_ctrl / dt_plant:

* observation: rho and v are restricted to the controller's nodes by full weighting (the average
  with hat weights (r - |j|) / r^2 over the 2 r - 1 plant nodes around each controller node,
  renormalised at the two ends: the adjoint of linear interpolation); h_prev is the field the
  controller itself sent last, on its own nodes;
* the controller sees its own nominal (the plant's physical constants on its grid and period) and
  a delay buffer of the fields it has sent, one entry per control period;
* action: its time gap, saturated on its own nodes, is interpolated linearly to the plant's nodes
  and held for s plant steps (the controller acts at plant steps 0, s, 2 s, ...). An output that is not
  finite anywhere (NaN, inf) reaches the plant as NaN, so the closed loop refuses the step (reason
  ``Divergence.CONTROL``) exactly as for the controller acting directly.

With r = s = 1 the adapted controller equals the controller itself (tested). A plant coarser than
the controller, or a ratio that is not an integer, is a ``ValueError``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic.control.base import Controller, Observation, saturate
from jaxtraffic.model import delay as delay_buffer
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.model.spatial import prolong, restrict

Array = jax.Array


@dataclasses.dataclass(frozen=True)
class ControllerGrid:
    """A controller's own discretisation: ``n_points`` nodes over the road, control period ``dt``
    (s) and the capacity of its buffer of sent fields (``max_delay_steps`` control periods)."""

    n_points: int = 201
    dt: float = 0.1
    max_delay_steps: int = 100

    @classmethod
    def of(cls, p: TrafficParams) -> ControllerGrid:
        """The grid of a (concrete) nominal: its n_points, dt and max_delay_steps."""
        return cls(n_points=p.n_points, dt=float(p.dt), max_delay_steps=p.max_delay_steps)

    def nominal(self, plant_nominal: TrafficParams, period_steps: int = 1) -> TrafficParams:
        """``plant_nominal``'s physical constants on this grid (one solver step per period, which is
        ``period_steps`` plant steps)."""
        dt = plant_nominal.dt if period_steps == 1 else self.dt
        return plant_nominal.replace(n_points=self.n_points, dt=dt, max_delay_steps=self.max_delay_steps, substeps=1)


PAPER_GRID = ControllerGrid()  # the paper's grid (5 m, 0.1 s): the baselines' design grid


def baseline_grid(plant: TrafficParams) -> ControllerGrid:
    """The grid a baseline (open loop, Lyapunov, backstepping) acts on over ``plant``: the paper's
    whenever the plant's grid and step refine it, else the plant's own (e.g. a tiny test grid)."""
    try:
        ratios(PAPER_GRID, plant)
    except ValueError:
        return ControllerGrid.of(plant)
    return PAPER_GRID


def ratios(grid: ControllerGrid, plant: TrafficParams) -> tuple[int, int]:
    """(r, s): plant nodes per controller cell and plant steps per control period; ``ValueError``
    unless both are integers >= 1."""
    if (plant.n_points - 1) % (grid.n_points - 1):
        raise ValueError(f"the plant's grid ({plant.n_points} points) does not refine the controller's "
                         f"({grid.n_points} points) by an integer factor: need (n_plant - 1) a multiple of "
                         f"(n_controller - 1) = {grid.n_points - 1}")
    s = grid.dt / float(plant.dt)
    if round(s) < 1 or abs(s - round(s)) > 1e-6 * s:
        raise ValueError(f"the controller's period dt = {grid.dt} s is not a whole number of plant steps "
                         f"(dt = {float(plant.dt)} s)")
    return (plant.n_points - 1) // (grid.n_points - 1), int(round(s))


@struct.dataclass
class AdaptedState:
    """The adapted controller's state: the inner controller's, the field it sent last on its own
    nodes (s), its buffer of sent fields, the field the plant receives (s) and the plant step count."""

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> AdaptedState: ...

    inner: Any
    h_ctrl: Array
    sent: delay_buffer.DelayBuffer
    h_plant: Array
    step: Array


def adapt(controller: Controller, grid: ControllerGrid, plant: TrafficParams) -> Controller:
    """``controller``, built on ``grid``, acting on the (concrete) discretisation of ``plant``
    (module docstring). On the controller's own grid and period it acts exactly as the controller
    itself (through its own buffer of sent fields)."""
    return on_grid(controller, grid, *ratios(grid, plant))


def on_grid(controller: Controller, grid: ControllerGrid, r: int, s: int) -> Controller:
    """``adapt`` with the ratios given (static ints: plant nodes per controller cell r, plant steps per
    control period s), for a plant that is traced; ``grid.dt`` is then not used when s = 1 (the
    controller's period is the plant's dt)."""
    act, init = _on_grid_fns(controller.act_fn, controller.init_fn, grid, r, s)
    return Controller(settings=controller.settings, act_fn=act, init_fn=init,
                      name=f"{controller.name} ({grid.n_points} points, {grid.dt:g} s)")


@functools.cache
def _on_grid_fns(inner_act: Callable, inner_init: Callable, grid: ControllerGrid, r: int, s: int
                 ) -> tuple[Callable, Callable]:
    """``on_grid``'s (act_fn, init_fn), one pair per inner law and grid: the same functions for every controller
    adapted alike, so that a compiled rollout is reused for new settings, not traced and compiled again (a training
    that validates each checkpoint would otherwise load a program per validation until the process runs out of
    memory mappings)."""

    def view(obs: Observation, nominal: TrafficParams, h_prev: Array,
             sent: delay_buffer.DelayBuffer) -> tuple[Observation, TrafficParams]:
        sub = Observation(rho=restrict(obs.rho, r), v=restrict(obs.v, r), h_prev=h_prev, t=obs.t, sent=sent)
        return sub, grid.nominal(nominal, s)

    def init(settings, obs, nominal):
        h0 = jnp.full((grid.n_points,), nominal.h_bar, obs.rho.dtype)
        sent = delay_buffer.init_buffer(h0, grid.max_delay_steps)
        sub, nom = view(obs, nominal, h0, sent)
        return AdaptedState(inner=inner_init(settings, sub, nom), h_ctrl=h0, sent=sent,
                            h_plant=jnp.full_like(obs.rho, nominal.h_bar), step=jnp.zeros((), jnp.int32))

    def act(settings, cs: AdaptedState, obs, nominal, key):
        sub, nom = view(obs, nominal, cs.h_ctrl, cs.sent)
        h, inner_state = inner_act(settings, cs.inner, sub, nom, key)
        finite = jnp.all(jnp.isfinite(h))  # a NaN/inf output reaches the plant as NaN: refused there, not hidden
        h = saturate(h, nom).astype(obs.rho.dtype)
        now = cs.step % s == 0
        new = AdaptedState(inner=inner_state, h_ctrl=h, sent=delay_buffer.push(cs.sent, h),
                           h_plant=jnp.where(finite, prolong(h, r), jnp.nan), step=cs.step + 1)
        if s > 1:  # between two control instants the previous field is held
            new = jax.tree.map(lambda a, b: jnp.where(now, a, b), new, cs.replace(step=cs.step + 1))
        return new.h_plant, new

    return act, init
