"""The main job's training runs as data: one TOML configuration per run (``train.py --recipe NAME`` or
``train.py --config FILE`` trains one on its own), loaded by ``recipe(name)``.

    ppo.toml               the paper's PPO policy at D = 4 s on the paper's grid
    gradient-gains.toml    three constant gains trained by Adam through the reference plant
    gradient-network.toml  the actor network trained by Adam through the reference plant
    gradient-robust.toml   the robust delay schedule, trained by CEM over the robustness map's ranges
    adaptive-residual.toml a learned correction on adaptive backstepping, trained by CEM as the schedule

``evaluate.py`` sets each run's directory and, from its own grids, the training plant (``training_plant``).
"""

from __future__ import annotations

import tomllib
from importlib import resources
from typing import Any

from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.config.toml import tables_of_toml

NAMES = ("ppo", "gradient-gains", "gradient-network", "gradient-robust", "adaptive-residual")


def recipe_tables(name: str) -> dict[str, dict[str, Any]]:
    """The fields the recipe ``name`` (one of ``NAMES``) gives, by table, as a config file's
    (``runs.config.toml.read_tables``); ``ValueError`` naming the recipes for another name."""
    if name not in NAMES:
        raise ValueError(f"no recipe {name!r}; the recipes are: {', '.join(NAMES)}")
    where = f"jaxtraffic/paper/recipes/{name}.toml"
    text = resources.files(__package__).joinpath(f"{name}.toml").read_text()
    return tables_of_toml(tomllib.loads(text), where)


def recipe(name: str) -> TrainConfig:
    """The configuration of the main job's run ``name`` (one of ``NAMES``); an error names its file."""
    where = f"jaxtraffic/paper/recipes/{name}.toml"
    tables = recipe_tables(name)
    try:
        return TrainConfig.make(**tables)
    except (TypeError, ValueError) as err:  # (a message of tables_of_toml names the file already)
        raise ValueError(err if str(err).startswith(where) else f"{where}: {err}") from None


def training_plant(kind: str, controller_points: int, reference: tuple[int, int]) -> dict[str, dict]:
    """The training plant of a gradient recipe as config tables (``TrainConfig.updated``): ``kind``
    "reference" is the reference plant (MUSCL, ``reference`` = (points, substeps)); "half" is MUSCL on the
    controller's grid refined once (it agrees with the reference plant on which high-alpha plants diverge at a
    quarter of its cost, docs/model.md section 17). The controller acts on its own grid of ``controller_points``
    nodes."""
    if kind == "reference":
        n_points, substeps = reference
    elif kind == "half":
        n_points, substeps = 2 * (controller_points - 1) + 1, 1
    else:
        raise ValueError(f"training plant kind must be 'reference' or 'half', got {kind!r}")
    return {"plant": {"n_points": n_points, "scheme": "muscl", "substeps": substeps},
            "grad": {"controller_points": controller_points}}
