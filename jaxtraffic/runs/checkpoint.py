"""Atomic, checksummed, pickle-free checkpoints (flax msgpack serialization), run-directory I/O,
``load_policy``.

A checkpoint file is a msgpack map ``{"format": "jaxtraffic-checkpoint", "version": 1, "sha256":
<hex digest of payload>, "payload": <bytes>}`` whose payload is the flax-msgpack encoding of
``{"runner": <state dict of the PPO Runner>, "meta": <progress>}``; a PPO run's best.msgpack
(same format) holds each member's best-scoring policy (``params``, observation ``mean`` / ``var``,
``score``, ``env_steps``; ``runs.ppo.selection``), which ``load_policy`` loads by default. The loaders
check the digest, so a truncated, empty or corrupted file is an error naming it, never a silent load (files
written before the checksum, a bare payload, still load). Every file is written whole or not at
all (``jaxtraffic.io.files``: atomic writes, JSON with non-finite numbers).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import jax
import msgpack
import numpy as np
from flax import serialization

from jaxtraffic.io.files import atomic_write_bytes, read_regular, to_jsonable
from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.config.toml import migrate
from jaxtraffic.runs.config.tree import CONFIG_VERSION, run_control

CHECKPOINT = "checkpoint.msgpack"
CONFIG = "config.json"
SUMMARY = "summary.json"
BEST = "best.msgpack"
CHECKPOINT_LIMIT = 2**31  # bytes: a checkpoint holds a population's networks and optimiser states
_BEST_ARRAYS = ("mean", "var", "score", "env_steps")
FORMAT = "jaxtraffic-checkpoint"
FORMAT_VERSION = 1


def _write_checked(path: Path, state: dict) -> None:
    """Write a state dict atomically in the checksummed format (module docstring)."""
    payload = serialization.msgpack_serialize(state)
    wrapped = msgpack.packb({"format": FORMAT, "version": FORMAT_VERSION,
                             "sha256": hashlib.sha256(payload).hexdigest(), "payload": payload}, use_bin_type=True)
    atomic_write_bytes(path, wrapped)


def save_checkpoint(run_dir: str | Path, runner: Any, meta: dict) -> None:
    """Write the runner (all devices and seeds) and the progress ``meta`` atomically, with the
    sha256 of the payload."""
    state = {"runner": serialization.to_state_dict(jax.device_get(runner)), "meta": to_jsonable(meta)}
    _write_checked(Path(run_dir) / CHECKPOINT, state)


POLICY_ONLY = "policy_only"  # meta flag of an exported checkpoint: the policy without the optimiser state


def export_policy(run_dir: str | Path, out_dir: str | Path) -> bool:
    """Write ``run_dir``'s checkpoint in ``out_dir`` without its optimiser state, when it is a gradient-trained
    run's (a runner of ``theta`` and ``opt_state``): what ``load_policy`` reads, a third of the bytes of a
    network's checkpoint. Such a file loads but cannot be resumed (``restore_runner`` says so). Returns False,
    writing nothing, for any other checkpoint (a PPO runner, whose policy an export takes from best.msgpack) and
    for one that is a symbolic link, missing or unreadable (the caller copies it as it is, or not at all)."""
    path = Path(run_dir) / CHECKPOINT
    if path.is_symlink() or not path.is_file():
        return False
    try:
        runner, meta = load_checkpoint(run_dir)
    except ValueError:  # not a checkpoint this version reads: load_policy will say what is wrong with the copy
        return False
    if not {"theta", "opt_state"} <= set(runner):
        return False
    state = {"runner": {k: v for k, v in runner.items() if k != "opt_state"}, "meta": {**meta, POLICY_ONLY: True}}
    _write_checked(Path(out_dir) / CHECKPOINT, state)
    return True


def _broken(path: Path, why: str) -> ValueError:
    return ValueError(f"{path}: {why}; the checkpoint cannot be used (restore it from a copy, or retrain "
                      "without --resume in a new --out-dir)")


def load_checkpoint(run_dir: str | Path) -> tuple[dict, dict]:
    """(runner state dict, meta) of ``run_dir``'s checkpoint; ``ValueError`` naming the file if it is
    empty, truncated, corrupted (checksum) or not a checkpoint."""
    path = Path(run_dir) / CHECKPOINT
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}")
    state = _read_checked(path, legacy_key="runner")
    if not (isinstance(state, dict) and isinstance(state.get("runner"), dict) and isinstance(state.get("meta"), dict)
            and isinstance(state["meta"].get("env_steps"), int)):
        raise _broken(path, "not a jaxtraffic checkpoint (no runner state and progress)")
    _check_meta(path, state["meta"])
    return state["runner"], state["meta"]


def _count(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and 0 <= x < 2**62


def _seconds(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and 0 <= x < float("inf")


def _problem(x: Any) -> bool:
    try:
        return x is None or isinstance(json.loads(x), dict)
    except (TypeError, ValueError, RecursionError):
        return False


def _check_meta(path: Path, meta: dict) -> None:
    """``_broken`` unless the checkpoint's progress (``loop.Progress.to_meta``) holds what a run writes: counts
    (int >= 0), seconds (finite >= 0 or null), a flag, rows and the trained problem: a crafted file with a valid
    checksum is refused before anything is rewritten."""
    rules = {"env_steps": _count, "updates": _count, "wall_s": _seconds, "stopped": lambda x: isinstance(x, bool),
             "rows": lambda x: isinstance(x, list) and all(isinstance(r, dict) for r in x), PROBLEM: _problem,
             POLICY_ONLY: lambda x: x is True}
    for key, value in meta.items():
        ok = rules.get(key)
        if ok is None and key.startswith("seconds_to_"):
            ok = lambda x: x is None or _seconds(x)  # noqa: E731
        elif ok is None and key.startswith(("env_steps_to_", "updates_to_")):
            ok = lambda x: x is None or _count(x)  # noqa: E731
        if ok is not None and not ok(value):
            raise _broken(path, f"its progress is not what a run writes ({key} = {str(value)[:60]!r})")


def _read_checked(path: Path, legacy_key: str) -> Any:
    """The state dict of a file in the checksummed format (or, written before the checksum, a bare
    payload holding ``legacy_key``); ``ValueError`` naming the file if it is broken."""
    data = read_regular(path, CHECKPOINT_LIMIT)  # a regular file only
    if not data:
        raise _broken(path, "empty file")
    try:
        outer = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as err:  # noqa: BLE001 - msgpack raises several unrelated types
        raise _broken(path, f"truncated or not msgpack ({type(err).__name__}: {err})") from None
    if isinstance(outer, dict) and outer.get("format") == FORMAT:
        payload = outer.get("payload")
        if not isinstance(payload, bytes) or not isinstance(outer.get("sha256"), str):
            raise _broken(path, "malformed checkpoint (no payload or checksum)")
        if outer.get("version") != FORMAT_VERSION:
            raise _broken(path, f"checkpoint format version {outer.get('version')!r}, this jaxtraffic reads "
                                f"{FORMAT_VERSION}")
        if hashlib.sha256(payload).hexdigest() != outer["sha256"]:
            raise _broken(path, "checksum mismatch (the file is corrupted)")
    elif isinstance(outer, dict) and legacy_key in outer:
        payload = data  # written before the checksum
    else:
        raise _broken(path, "not a jaxtraffic checkpoint")
    try:
        return serialization.msgpack_restore(payload)
    except Exception as err:  # noqa: BLE001
        raise _broken(path, f"payload cannot be decoded ({type(err).__name__}: {err})") from None


PROBLEM = "config_problem"  # the trained problem (``problem_of``), in the checkpoint's meta and in best.msgpack


def problem_of(config: TrainConfig) -> str:
    """What a checkpoint was trained on: every config field but the run control (``RUN_CONTROL`` and the
    gradient trainer's step count, which a resume may change), as canonical JSON, with its ``config_version``."""
    skip = run_control("gradient")
    return json.dumps(to_jsonable({"config_version": CONFIG_VERSION, **{
        s: {k: v for k, v in table.items() if k not in skip.get(s, ())} for s, table in config.tables().items()}}),
        sort_keys=True)


def check_problem(config: TrainConfig, stored: Any, path: Path) -> None:
    """``ValueError`` if ``path`` (a checkpoint holding ``stored``, its ``problem_of`` at training time) was
    trained on another problem than ``config`` says; files written before the binding hold none."""
    if not isinstance(stored, str):
        return
    saved, now = _fields(_today(json.loads(stored), path)), _fields(json.loads(problem_of(config)))
    diff = [k for k in saved if k in now and saved[k] != now[k]]
    if diff:
        said = ", ".join(f"{k} = {now[k]!r}" for k in diff[:4])
        raise ValueError(f"{path.parent / 'config.toml'}: {said}, but {path.name} was trained with "
                         f"{', '.join(repr(saved[k]) for k in diff[:4])}: the two do not belong together "
                         "(the config edited after training, or taken from another run)")


def _today(problem: Any, path: Path) -> Any:
    """A stored ``problem_of`` brought to today's config version (``toml.migrate``; one written before it carried
    its version: 3 or 4, which the migrations from 3 both read right)."""
    if not isinstance(problem, dict):
        return problem
    version = problem.pop("config_version", 3)
    if not all(isinstance(t, dict) for t in problem.values()):  # written before the sections: compares with nothing
        return problem
    return migrate(problem, version, str(path))


def _fields(problem: Any) -> dict[str, Any]:
    """A ``problem_of`` as ``{"section.field": value}`` (one written before the sections, ``{field: value}``,
    compares with nothing: its run is refused by its config.json's version)."""
    return {f"{s}.{k}": v for s, table in problem.items() if isinstance(table, dict) for k, v in table.items()} \
        if isinstance(problem, dict) else {}


def save_best(run_dir: str | Path, state: dict, problem: str | None = None) -> None:
    """Write the per-member best checkpoints (``state``: a state dict with params, obs mean/var, score,
    env_steps; ``ppo.selection.BestCheckpoints.state_dict``) atomically, with the trained problem
    (``problem_of``)."""
    _write_checked(Path(run_dir) / BEST, {**state, **({PROBLEM: problem} if problem else {})})


def load_best(run_dir: str | Path) -> dict | None:
    """The state dict of ``run_dir``'s best.msgpack, or None if the run has none."""
    path = Path(run_dir) / BEST
    if not path.exists():
        return None
    state = _read_checked(path, legacy_key="params")
    if not (isinstance(state, dict) and isinstance(state.get("params"), dict)
            and all(k in state for k in _BEST_ARRAYS)):
        raise _broken(path, "not a best-checkpoint file (no params, statistics and scores)")
    return state


def restore_runner(template: Any, state: dict, path: str | Path = CHECKPOINT) -> Any:
    """Fill ``template`` (a Runner of the right structure) with a loaded state dict; ``ValueError``
    naming ``path`` if the structure or a shape differs (another grid, network, number of seeds,
    environments or devices)."""
    want = serialization.to_state_dict(template)
    flat_want = dict(_flatten(want))
    flat_have = dict(_flatten(state))
    if set(flat_want) != set(flat_have):
        if "theta" in state and "opt_state" not in state:
            raise ValueError(f"{path} holds a policy without its optimiser state (exported by evaluate.py into "
                             "results/runs): load_policy loads it, but it cannot be resumed; resume the run it "
                             "was exported from")
        missing = sorted(set(flat_want) - set(flat_have))[:3]
        extra = sorted(set(flat_have) - set(flat_want))[:3]
        raise ValueError(f"{path}: the saved state does not match this configuration (missing {missing}, "
                         f"unexpected {extra}); was it written with another network or jaxtraffic version?")
    if "update" in flat_want and np.ndim(flat_want["update"]) >= 1:  # PPO: shape (devices, seeds)
        check_device_count(state, np.shape(flat_want["update"])[0], path)
    for k, w in flat_want.items():
        if np.shape(w) != np.shape(flat_have[k]):
            raise ValueError(f"{path}: saved {k} has shape {np.shape(flat_have[k])}, this configuration needs "
                             f"{np.shape(w)} (config.json and the checkpoint do not belong together: another grid, "
                             "network, number of seeds or environments)")
    return serialization.from_state_dict(template, state)


def check_device_count(state: dict, n_devices: int, path: str | Path = CHECKPOINT) -> None:
    """``ValueError`` (explaining what to do) if the checkpoint's runner was split over another
    number of devices than ``n_devices`` (every leaf has a leading device axis)."""
    update = state.get("update") if isinstance(state, dict) else None
    saved = np.shape(update)[0] if update is not None and np.ndim(update) >= 1 else None
    if saved is not None and saved != n_devices:
        raise ValueError(f"{path} was written by a run with {saved} device(s), this one has {n_devices}: "
                         f"resume with {saved} device(s) in all processes together (on CPU, one process: "
                         f"XLA_FLAGS=--xla_force_host_platform_device_count={saved}); the environments are split "
                         "between the devices, so the saved state only continues on as many")


def _flatten(tree: Any, prefix: str = "") -> list[tuple[str, Any]]:
    if isinstance(tree, dict):
        out = []
        for k, v in tree.items():
            out += _flatten(v, f"{prefix}/{k}" if prefix else str(k))
        return out
    return [(prefix, tree)]
