#!/usr/bin/env python
"""Train jaxtraffic's gain environment with Stable-Baselines3's PPO (PyTorch).

``SB3VecEnv`` (``jaxtraffic.ecosystem.sb3``) hands the whole batch of environments to one
jit-compiled, vmapped JAX step (SB3's ``DummyVecEnv`` would step them one by one in Python);
``VecMonitor`` adds SB3's episode statistics. Actions are normalised gains in [-1, 1]^3.

    pip install torch --index-url https://download.pytorch.org/whl/cpu   # the CPU build (optional)
    pip install -e ".[sb3]"          # gymnasium + stable-baselines3 (+ torch)
    python examples/sb3_ppo.py --n-points 51 --num-envs 64 --total-timesteps 200000 --save runs/sb3_ppo.zip
    python examples/sb3_ppo.py --help

Judged next to backstepping and PPO on every experiment of the paper (REPORT.md's tables):

    python evaluate.py --controller sb3=examples/sb3_ppo.py:controller:runs/sb3_ppo.zip

(``controller`` below: the saved model's ``predict`` through ``jaxtraffic.ecosystem.policy_as_controller``,
on the grid it was trained on; ``--save`` writes the environment's settings beside the model, PATH.json).
``tests/test_ecosystem_gym.py`` runs this example for a few hundred steps (CI installs the extra).
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> dict:
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    from jaxtraffic.ecosystem.sb3 import SB3VecEnv

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-points", type=int, default=51, help="grid points of the traffic PDE")
    ap.add_argument("--horizon-s", type=float, default=10.0, help="episode length, s")
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument("--n-steps", type=int, default=100, help="rollout steps per environment and update")
    ap.add_argument("--total-timesteps", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", type=Path, default=None, help="write the model here (and its environment, PATH.json)")
    args = ap.parse_args(argv)
    env_config = {"n_points": args.n_points, "horizon_s": args.horizon_s}
    venv = VecMonitor(SB3VecEnv(num_envs=args.num_envs, **env_config))
    batch = args.num_envs * args.n_steps
    model = PPO("MlpPolicy", venv, n_steps=args.n_steps, batch_size=min(batch, 4096), n_epochs=4,
                learning_rate=1e-3, gamma=0.995, gae_lambda=0.95, seed=args.seed, device="cpu", verbose=0)
    t0 = time.perf_counter()
    model.learn(total_timesteps=args.total_timesteps)
    wall = time.perf_counter() - t0
    returns = [ep["r"] for ep in model.ep_info_buffer]
    rate = model.num_timesteps / wall
    print(f"SB3 PPO on jaxtraffic/Gain-v0: {model.num_timesteps} env steps in {wall:.1f} s ({rate:,.0f} steps/s, "
          f"compilation included); mean return of the last {len(returns)} episodes: "
          f"{sum(returns) / max(1, len(returns)):.3f}")
    venv.close()
    if args.save is not None:
        model.save(args.save)
        args.save.with_suffix(".json").write_text(json.dumps(env_config))
        print(f"saved {args.save} (+ {args.save.with_suffix('.json').name}); judge it with: python evaluate.py "
              f"--controller sb3=examples/sb3_ppo.py:controller:{args.save}")
    return {"model": model, "num_timesteps": model.num_timesteps, "steps_per_s": rate, "returns": returns}


def _predict(model, obs):
    return model.predict(obs, deterministic=True)[0]


def controller(path: str = "runs/sb3_ppo.zip"):
    """(Controller, ControllerGrid) of a model saved by ``--save``: for ``evaluate.py --controller``."""
    from stable_baselines3 import PPO

    from jaxtraffic.ecosystem import controller_grid, policy_as_controller

    config = json.loads(Path(path).with_suffix(".json").read_text())
    model = PPO.load(path, device="cpu")
    fn = functools.partial(_predict, model)  # SB3's predict takes one observation or a batch
    return policy_as_controller(fn, name="sb3_ppo", batched=True, **config), controller_grid(**config)


if __name__ == "__main__":
    main()
