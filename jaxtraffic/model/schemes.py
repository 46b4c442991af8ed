"""The table of numerical schemes: the one place where the user-facing name ``TrafficParams.scheme``
is mapped to its composed pieces (a ``model.reconstruction``, a ``model.time_stepping`` tableau and
the ``model.boundary`` conditions). Adding a scheme is one entry in ``SCHEMES``.
"""

from __future__ import annotations

import dataclasses

from jaxtraffic.model import boundary
from jaxtraffic.model.reconstruction import FIRST_ORDER_UPWIND, MUSCL_MINMOD, Reconstruction
from jaxtraffic.model.time_stepping import FORWARD_EULER, SSP_RK2, ShuOsherTableau


@dataclasses.dataclass(frozen=True)
class Scheme:
    """A finite-volume scheme: spatial discretisation, time integrator, inlet and outlet conditions."""

    reconstruction: Reconstruction
    integrator: ShuOsherTableau
    inlet: boundary.Inlet = boundary.INFLOW_DENSITY
    outlet: boundary.Outlet = boundary.SPEED_ODE


SCHEMES: dict[str, Scheme] = {
    "upwind": Scheme(FIRST_ORDER_UPWIND, FORWARD_EULER),  # the paper's method
    "muscl": Scheme(MUSCL_MINMOD, SSP_RK2),
}
SCHEME_NAMES = tuple(SCHEMES)


def get_scheme(name: str) -> Scheme:
    """The composed scheme called ``name`` (``TrafficParams.scheme``).

    Raises:
        ValueError: for an unknown name, listing the known ones.
    """
    try:
        return SCHEMES[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown scheme {name!r}: known schemes are {SCHEME_NAMES}") from None
