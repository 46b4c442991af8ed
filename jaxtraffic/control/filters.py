"""A measurement filter on any control law (docs/model.md section 20): the law sees the density and speed fields
through a Gaussian filter of width sigma (m), as the learned laws do (``gain_law``'s ``filter_sigma``), so that a
model-based law and a learned one can be compared on the same measurements."""

from __future__ import annotations

import functools
from collections.abc import Callable

from jaxtraffic.control.base import Controller
from jaxtraffic.control.gain_law import sigma_nodes
from jaxtraffic.model.spatial import smooth

__all__ = ["measurement_filter"]


@functools.cache
def _filtered(act_fn: Callable, init_fn: Callable, nodes: float) -> tuple[Callable, Callable]:
    """(act_fn, init_fn) of a law seeing its observation filtered (cached: one function per law and width, so that
    equal filtered laws compile once)."""
    def view(obs):
        return obs.replace(rho=smooth(obs.rho, nodes), v=smooth(obs.v, nodes))

    def act(settings, cstate, obs, nominal, key):
        return act_fn(settings, cstate, view(obs), nominal, key)

    def init(settings, obs, nominal):
        return init_fn(settings, view(obs), nominal)

    return act, init


def measurement_filter(controller: Controller, filter_sigma: float, dx: float = 5.0) -> Controller:
    """``controller`` acting on rho and v filtered by a Gaussian of width ``filter_sigma`` (m, static; 0: the law
    itself) on its grid of spacing ``dx`` (m; the paper's 5 m). A constant field passes unchanged, a wave of
    wavelength lambda is multiplied by about exp(-(2 pi sigma / lambda)^2 / 2) (0.82 for 250 m at 25 m). Its
    settings are the law's own (``tell_delay`` still applies)."""
    nodes = sigma_nodes(filter_sigma, dx)
    if nodes == 0:
        return controller
    act, init = _filtered(controller.act_fn, controller.init_fn, nodes)
    return controller.replace(act_fn=act, init_fn=init, name=f"{controller.name} (sigma {filter_sigma:g} m)")
