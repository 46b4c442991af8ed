"""``evaluate.py``'s options as a dataclass; its command line is derived from it by tyro (``parse_evaluate``).

tyro (the choice of cleanrl and much JAX RL code) turns a typed dataclass into a parser: each field is a flag
(``run_delay0`` is ``--run-delay0``), its docstring the help, its default the default; prefixes of flags are not
accepted. Flags renamed since the last release fail with one line naming the new flag (``RENAMED``).
"""

from __future__ import annotations

import inspect
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from jaxtraffic.model.params import TrafficParams
from jaxtraffic.paper.fair import N_OTHER, N_TEST

_REF = TrafficParams.reference()


@dataclass
class Cluster:
    """Multi-process runs (``jax.distributed``); default: the JAX_* environment variables."""

    coordinator_address: str | None = None
    """process 0's coordinator service, HOST:PORT ($JAX_COORDINATOR_ADDRESS)"""
    num_processes: int | None = None
    """number of processes ($JAX_NUM_PROCESSES)"""
    process_id: int | None = None
    """this process's id, 0 .. N-1 ($JAX_PROCESS_ID)"""

    def values(self) -> tuple[str | None, int | None, int | None]:
        """The arguments of ``platform.distributed.initialize``."""
        return self.coordinator_address, self.num_processes, self.process_id


@dataclass
class EvaluateOptions:
    """Reproduce the paper's section 4 on the paper's grid and on the reference plant: every scenario, the
    robustness maps, figures, Table 2, metrics.json and REPORT.md, training the missing controllers first."""

    run: Path | None = None
    """PPO run trained with D = 4 s (default runs/default, trained first if missing)"""
    run_delay0: Path | None = None
    """optional PPO run trained with D = 0, for scenario delay0"""
    out: Annotated[Path, tyro.conf.arg(aliases=("--out-dir",))] = Path("results")
    """output folder (created by the job; a non-empty one must hold an earlier report of ours); --out-dir is the
    same flag (train.py's name)"""
    n_points: int | None = None
    """grid points of the paper plant (default: the PPO run's)"""
    horizon: float = 300.0
    """simulated time of each scenario, s"""
    noise_seeds: int = 8
    """noise seeds of the alpha-noise scenario"""
    robust_grid: str = "17x12"
    """robustness map on the paper plant, DELAYSxALPHAS over 0-8 s x 0.05-0.6 (0x0: skip it)"""
    robust_horizon: float | None = None
    """simulated time of the robustness maps, s (default 2 x --horizon)"""
    gradient: Literal["auto", "existing", "none"] = "auto"
    """gradient-trained controllers: train the missing ones (auto), only those trained, or none"""
    runs_root: Path = Path("runs")
    """where the gradient-trained runs live"""
    plants: str = "paper,reference"
    """the plants every experiment runs on: paper, reference, or both"""
    reference_grid: str = f"{_REF.n_points}x{_REF.substeps}"
    """the reference plant (MUSCL), POINTSxSUBSTEPS; also the gradient runs' training plant"""
    reference_robust_grid: str = "9x6"
    """robustness map on the reference plant, DELAYSxALPHAS"""
    fair: int = N_TEST
    """test scenarios of the held-out comparison of every law on the first plant, 600 s (0: skip it)"""
    fair_other: int = N_OTHER
    """test scenarios of the held-out comparison on each other plant of --plants, 600 s (0: skip it)"""
    tuned: Path = Path("docs/results/fair/tuned.json")
    """the model-based laws' parameters tuned on the train split (tune_baselines.py; absent: no tuned rows)"""
    split_runs: Path | None = None
    """learned runs trained on the train split over seeds to add to the comparison (benchmarks/train_split_sweep.py)"""
    oracle_dir: Path = Path("docs/results/oracle")
    """oracle rows of the maps (PLANT.json of benchmarks/gain_oracle.py); a missing file leaves them out"""
    controller: tuple[str, ...] = ()
    """NAME=SOURCE:FUNCTION[:ARG]: also judge your own controller. This RUNS the file's (or module's) code with
    your permissions, like `python FILE`: only give code you trust"""
    controller_normalization: tuple[str, ...] = ()
    """NAME=FILE: the observation statistics of SB3's VecNormalize the --controller NAME was trained under
    (FILE written by jaxtraffic.ecosystem.normalization.export_obs_normalization; no pickle is read). A
    vecnormalize*.pkl next to the controller's model without this flag is refused"""
    judge: bool = False
    """judge only the --controller policies against the baselines (open loop, Lyapunov, backstepping, adaptive
    backstepping) on every scenario and plant: no training, no learned controller of jaxtraffic (for that
    comparison leave --judge out: the main job judges --controller beside PPO and the gradient-trained runs,
    training those missing)"""
    numerics_check: bool = True
    """rerun Table 2's scenario on each plant refined twice and with the other scheme"""
    cluster: Annotated[Cluster, tyro.conf.OmitArgPrefixes] = field(default_factory=Cluster)


# flags of the last release that are gone: old flag -> the new one
RENAMED = {"--seeds": "--noise-seeds"}


def refuse_renamed(argv: list[str], renamed: dict[str, str], prog: str) -> None:
    """``SystemExit(2)`` with one line naming the new flag when ``argv`` uses a flag of ``renamed``."""
    for arg in argv:
        old = arg.split("=", 1)[0]
        if old in renamed:
            print(f"{prog}: error: {old} was renamed {renamed[old]}", file=sys.stderr)
            raise SystemExit(2)


def parse_evaluate(argv: list[str] | None, prog: str) -> EvaluateOptions:
    """The options of the command line ``argv`` (default ``sys.argv[1:]``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    refuse_renamed(argv, RENAMED, prog)
    exit_on_version(argv, prog)
    return tyro.cli(EvaluateOptions, args=argv, prog=prog, config=(tyro.conf.UseAppendAction,),
                    description=inspect.cleandoc(EvaluateOptions.__doc__ or "") + " --version: the version.")


def version() -> str:
    """The package's version as written in ``jaxtraffic._version`` (an editable install's metadata can be stale)."""
    from jaxtraffic._version import __version__

    return __version__


def exit_on_version(argv: list[str], prog: str) -> None:
    """``--version`` anywhere in ``argv``: print ``PROG VERSION`` and exit 0 (both programs)."""
    if "--version" in argv:
        print(f"{prog} {version()}")
        raise SystemExit(0)


def program(default: str) -> str:
    """The program's name as the user typed it (``jaxtraffic-evaluate``, ``evaluate.py``, ``python -m jaxtraffic
    train`` for ``default`` train.py), else ``default``."""
    path = Path(sys.argv[0]) if sys.argv and sys.argv[0] else None
    if path is not None and path.name == "__main__.py" and path.parent.name == "jaxtraffic":  # python -m jaxtraffic
        return f"python -m jaxtraffic {Path(default).stem}"
    name = path.name if path is not None else ""
    return name if name and name not in ("-c", "-m", "__main__.py", "pytest") and not name.startswith("pytest") \
        else default
