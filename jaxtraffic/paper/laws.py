"""One registry of the control laws the experiments compare (docs/model.md section 20).

Each law is declared once, as a ``Law``: its name (the key of every results file), its labels (``label`` in tables,
``short`` in figure legends) and line ``style``, what it is told of the plant ("nothing", "delay": each plant's D,
"delay_alpha": D and alpha), how it is made (a model-based law: ``build()``; a learned one: the ``recipe`` that
trains it and the plant it trains on, loaded from its run by evaluate.py), where it runs (``scope``: "all", the
paper's scenarios and the robustness map; "map", the map only), whether it runs a predictor (the map deals its
batch by delay) and its role on the map. The scenarios, the maps, REPORT.md, the judge, the figures and the
tables read their laws and labels from ``LAWS``; ``register`` adds one (a user's law appears in the maps and the
report with no other edit).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from jaxtraffic.compare.tuning import Tunable
from jaxtraffic.control import Controller, adaptive_backstepping, backstepping, lyapunov, measurement_filter, open_loop

CTRL_DELAY = 4.0  # s: the delay the model-based laws assume in the paper's scenarios (as the paper)
FILTER_M = 25.0  # m: the learned laws' measurement filter, given to the tuned model-based laws too
TOLD = ("nothing", "delay", "delay_alpha")
TOLD_TEXT = {"nothing": "nothing", "delay": "D", "delay_alpha": "D, alpha"}


@dataclasses.dataclass(frozen=True)
class Law:
    """A control law of the comparison (module docstring)."""

    name: str
    label: str
    short: str = ""
    style: dict[str, Any] | None = None
    told: str = "nothing"
    build: Callable[[], Controller] | None = None  # model-based: its controller on the paper's grid
    recipe: str | None = None  # learned by gradient: paper.recipes' name (its run folder under --runs-root)
    train_plant: str | None = None  # ... and the plant its recipe trains on (paper.recipes.training_plant)
    scope: str = "all"
    predictor: bool = False
    role: str = ""

    def __post_init__(self) -> None:
        if self.told not in TOLD:
            raise ValueError(f"law {self.name}: told must be one of {TOLD}, got {self.told!r}")
        if self.scope not in ("all", "map"):
            raise ValueError(f"law {self.name}: scope must be 'all' or 'map', got {self.scope!r}")
        if not self.name.isidentifier():
            raise ValueError(f"law name {self.name!r}: must be an identifier (a key of the results files)")

    @property
    def learned(self) -> bool:
        return self.build is None


LAWS: dict[str, Law] = {}


def register(law: Law) -> Law:
    """Add ``law`` to ``LAWS`` (a ``ValueError`` if its name is taken); returns it."""
    if law.name in LAWS:
        raise ValueError(f"a law named {law.name!r} is registered already")
    LAWS[law.name] = law
    return law


def unregister(name: str) -> None:
    """Remove a law ``register`` added (tests, notebooks)."""
    LAWS.pop(name)


for _law in (
    Law("open_loop", "open loop", style=dict(color="0.35", ls="-"), build=open_loop),
    Law("lyapunov", "Lyapunov", style=dict(color="tab:orange", ls="-"), build=lambda: lyapunov(1.0)),
    Law("backstepping", "backstepping", style=dict(color="tab:blue", ls="-"), told="delay", predictor=True,
        build=lambda: backstepping(CTRL_DELAY, 1.0)),
    Law("adaptive_backstepping", "adaptive backstepping (alpha estimated online)", told="delay", scope="map",
        predictor=True, build=lambda: adaptive_backstepping(CTRL_DELAY),
        role="fair model-based competitor of a learned law told D only"),
    Law("backstepping_alpha", "backstepping told alpha (information bound)", told="delay_alpha", scope="map",
        predictor=True, build=lambda: adaptive_backstepping(CTRL_DELAY, adapt=False), role="information bound"),
    Law("ppo", "PPO", style=dict(color="tab:green", ls="-")),
    Law("grad_gains", "gradient: 3 constant gains", "gradient gains", dict(color="tab:purple", ls="--"),
        recipe="gradient-gains", train_plant="reference"),
    Law("grad_network", "gradient: network", "gradient network", dict(color="tab:brown", ls="-."),
        recipe="gradient-network", train_plant="reference"),
    Law("grad_robust", "gradient: delay schedule (robust)", "gradient delay schedule (robust)",
        dict(color="tab:pink", ls=":"), told="delay", recipe="gradient-robust", train_plant="half"),
    Law("grad_residual", "learned residual on adaptive backstepping", "learned residual (adaptive)",
        dict(color="tab:olive", ls="--"), told="delay", recipe="adaptive-residual", train_plant="half",
        predictor=True),
):
    register(_law)


def label(name: str) -> str:
    """A law's table label (a name not registered, e.g. a user's --controller: the name itself)."""
    return LAWS[name].label if name in LAWS else name


def short_label(name: str) -> str:
    """A law's figure-legend label."""
    law = LAWS.get(name)
    return (law.short or law.label) if law else name


def names(*, learned: bool | None = None, scope: str | None = None) -> tuple[str, ...]:
    """The registered laws' names in registry order, filtered by kind and scope."""
    return tuple(n for n, law in LAWS.items() if (learned is None or law.learned == learned)
                 and (scope is None or law.scope == scope))


def recipes() -> dict[str, tuple[str, str]]:
    """The learned laws trained from a recipe: name -> (recipe, the plant it trains on)."""
    return {n: (law.recipe, law.train_plant or "paper") for n, law in LAWS.items() if law.recipe is not None}


def build_model_based(scope: str) -> dict[str, Controller]:
    """Every model-based law of ``scope`` built (on the paper's grid, default settings)."""
    return {n: LAWS[n].build() for n in names(learned=False, scope=scope)}  # type: ignore[misc]


# the model-based laws' design parameters, tuned on the train split (``compare.tuning``): the gain k and the share
# of w's damping kept, seeing the learned laws' 25 m measurements
BOUNDS = ((0.05, 3.0), (0.0, 1.0))
TUNABLE = {
    "backstepping": Tunable("backstepping", lambda d, k, keep: measurement_filter(backstepping(d, k, keep=keep),
                                                                                  FILTER_M),
                            ("k", "keep"), (1.0, 0.0), BOUNDS),
    "adaptive_backstepping": Tunable("adaptive_backstepping", lambda d, k, keep: measurement_filter(
        adaptive_backstepping(d, k, keep=keep), FILTER_M), ("k", "keep"), (1.0, 0.0), BOUNDS),
}
