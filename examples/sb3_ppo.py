#!/usr/bin/env python
"""Train jaxtraffic's gain environment with Stable-Baselines3's PPO (PyTorch).

``SB3VecEnv`` (``jaxtraffic.ecosystem.sb3``) hands the whole batch of environments to one
jit-compiled, vmapped JAX step (SB3's ``DummyVecEnv`` would step them one by one in Python);
``VecMonitor`` adds SB3's episode statistics. Actions are normalised gains in [-1, 1]^3.

    pip install -e ".[sb3]"          # gymnasium + stable-baselines3 (+ torch; a CPU wheel is enough)
    python examples/sb3_ppo.py --n-points 51 --num-envs 64 --total-timesteps 200000
    python examples/sb3_ppo.py --help

CI does not install the extra (torch is heavy): ``tests/test_ecosystem_gym.py`` runs this example
for a few hundred steps when stable-baselines3 is installed and skips it otherwise.
"""

from __future__ import annotations

import argparse
import time


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
    args = ap.parse_args(argv)
    venv = VecMonitor(SB3VecEnv(num_envs=args.num_envs, n_points=args.n_points, horizon_s=args.horizon_s))
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
    return {"model": model, "num_timesteps": model.num_timesteps, "steps_per_s": rate, "returns": returns}


if __name__ == "__main__":
    main()
