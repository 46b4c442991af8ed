"""Train every registered learned law on the scenario distribution's train split, over seeds (issue 47 item 5;
docs/model.md section 20): each law's recipe (``paper.recipes``) with ``--train-split N`` (its episodes or
scenarios drawn from N train-split scenarios, seed 0, instead of the paper's wave) and ``--seed S``, one run folder
per law and seed, ``OUT/<law>/seed<S>``. The CEM-trained laws (delay schedule, residual) get the tuned baselines'
budget and fitness (a population of 12 over 10 generations, 36 scenarios of 300 s, minimising the time-averaged
density L2: ``benchmarks/tune_baselines.py``, ``--cem-fitness mean_l2``, not their recipes' map counts); the
Adam-trained gains and network their recipes' steps on 12 scenarios (an Adam step sees every scenario); PPO 5
million environment steps by default (``--keep-going``; ``--ppo-steps 12960000`` gives it the CEM classes' budget
in plant-seconds: 12 x 10 x 36 rollouts of 300 s = 1.296 M s, against 5 M steps of 0.1 s = 0.5 M s), its best
checkpoint selected on its 36 train scenarios by the same measure over 300 s on the paper grid
(``runs.ppo.selection.make_split_suite``: the tuned baselines' objective, as a ratio to backstepping's; nothing of
the paper's wave). Then ``fair_benchmark.py --split-runs OUT`` judges them on the test split.

    python benchmarks/train_split_sweep.py --out runs-split --seeds 0 1 2      # about 45 min on 2 cores
    python benchmarks/train_split_sweep.py --out runs-ppo-matched --laws ppo --ppo-steps 12960000   # ~40 min
    python benchmarks/train_split_sweep.py --out runs-split-noise --sensor-noise 0 0.05   # each train scenario
                                                                  # seen with U(0, 0.05) sensor noise

``--sensor-noise LO HI`` has every trainer see each train scenario through the sensor noise the comparison's
``--sensor-noise`` draws (``EnvConfig.train_sensor_noise``): the gradient trainers the same levels and keys as
``tune_baselines.py --sensor-noise``; PPO each scenario's level, with fresh draws of the error in every episode
(its checkpoints selected on the split seen through those levels and keys).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from jaxtraffic.io.files import read_json
from jaxtraffic.paper import laws
from jaxtraffic.runs.config import load_config

ROOT = Path(__file__).resolve().parents[1]
MATCHED_PPO_STEPS = 12_960_000  # env steps of 0.1 s: the CEM classes' 1.296 M plant-seconds (12 x 10 x 36 x 300 s)
# law -> (train.py subcommand, recipe, extra flags); PPO is registered without a recipe (the main job trains it)
PLAN: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "ppo": ("ppo", "ppo", ("--train-split", "36", "--keep-going", "--max-wall-s", "3600",
                           "--val-plant", "training", "--val-horizon-s", "300")),
    "grad_gains": ("gradient", "gradient-gains", ("--train-split", "12")),
    "grad_network": ("gradient", "gradient-network", ("--train-split", "12")),
    "grad_robust": ("gradient", "gradient-robust", ("--train-split", "36", "--cem-population", "12",
                                                    "--train-horizon-s", "300", "--cem-fitness", "mean_l2")),
    "grad_residual": ("gradient", "adaptive-residual", ("--train-split", "36", "--cem-fitness", "mean_l2")),
}


def finished(run: Path) -> bool:
    """Whether the run in ``run`` trained to its end: its summary.json exists and does not say it was interrupted
    (a stopped run writes one too, and is resumed)."""
    return (run / "summary.json").exists() and not read_json(run / "summary.json").get("interrupted")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the runs' root folder")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--laws", nargs="+", default=list(PLAN), choices=list(PLAN))
    ap.add_argument("--ppo-steps", type=int, default=5_000_000,
                    help=f"PPO's environment steps (0.1 s each); {MATCHED_PPO_STEPS}: the CEM classes' plant-seconds")
    ap.add_argument("--sensor-noise", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="train every law seeing each scenario's relative sensor error drawn from U(LO, HI)")
    args = ap.parse_args()
    noise = ("--train-sensor-noise", *map(str, args.sensor_noise)) if args.sensor_noise else ()
    missing = [n for n in laws.names(learned=True) if n not in PLAN]
    if missing:
        print(f"note: registered learned laws without a sweep entry (not trained here): {missing}")
    for seed in args.seeds:
        for name in args.laws:
            algo, recipe, extra = PLAN[name]
            if name == "ppo":
                extra = (*extra, "--total-steps", str(args.ppo_steps))
            extra = (*extra, *noise)
            out = args.out / name / f"seed{seed}"
            if (out / "config.json").exists():  # a run trained with other noise is not this one
                seen = tuple(load_config(out).env.train_sensor_noise)
                if seen != tuple(args.sensor_noise or (0.0, 0.0)):
                    raise SystemExit(f"{out}: trained with sensor noise {seen}, not {args.sensor_noise}: another --out")
            if finished(out):
                print(f"{name} seed {seed}: done already ({out})", flush=True)
                continue
            cmd = [sys.executable, str(ROOT / "train.py"), algo, "--recipe", recipe, *extra, "--seed", str(seed),
                   "--out-dir", str(out), "--quiet", *(["--resume"] if out.exists() else [])]
            t0 = time.perf_counter()
            rc = subprocess.call(cmd, cwd=ROOT)
            print(f"{name} seed {seed}: rc {rc} in {time.perf_counter() - t0:.0f} s ({' '.join(cmd[2:])})", flush=True)


if __name__ == "__main__":
    main()
