"""The training loop and CLI (train.py, jaxtraffic/runs/ppo/trainer.py), checkpoints and policy loading,
on a tiny problem (21 nodes, 4 environments x 8 steps, 2 updates per chunk).

The training runs are the suite's one tiny training session (``tiny_runs.py``, started once per
session by the ``tiny_runs_root`` and ``two_device_proc`` fixtures of ``conftest.py``; the same runs
serve ``test_evaluate.py``): ``tiny_runs.train_runs`` (one CPU device, one compiled program shared
by every run) and ``tiny_runs.TWO_DEVICES`` (two forced host devices), in two subprocesses that
overlap on the 2 cores. The tests here read the run directories.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import leaves_equal
from tiny_runs import CHUNK, REPO, RUNS, TINY

from jaxtraffic.cli import train as train_cli
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import TrainConfig, load_config
from jaxtraffic.runs.config.tree import CONFIG_VERSION
from jaxtraffic.runs.curve import CURVE_FIELDS
from jaxtraffic.runs.policy import load_policy

SUMMARY_KEYS = {"env_steps", "wall_s", "seconds_to_stop_rule", "env_steps_to_stop_rule", "stop_rule_reached",
                "target_reward", "interrupted", "best_seed", "final_eval", "eval_horizon_s", "seconds_to_paper_rule",
                "env_steps_to_paper_rule", "min_wave_speed", "stopped", "best_val_score", "best_env_steps",
                "validation"}


def _rows(run: Path) -> list[dict]:
    with open(run / "learning_curve.csv", newline="") as f:
        return list(csv.DictReader(f))


def _no_wall(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows]




@pytest.fixture(scope="module")
def runs(tiny_runs_root):
    root = tiny_runs_root
    out = {k: root / k for k in RUNS}
    out["B_first_rows"] = _rows(root / "B_first")
    out["B_first_summary"] = json.loads((root / "B_first" / "summary.json").read_text())
    out["I_first_rows"] = _rows(root / "I_first")
    out["I_first_summary"] = json.loads((root / "I_first" / "summary.json").read_text())
    out["roundtrip"] = json.loads((root / "roundtrip.json").read_text())
    out["compiled_programs"] = json.loads((root / "done.json").read_text())["compiled_programs"]
    return out


def test_run_directory_contents(runs):
    run = runs["A"]
    for name in ("config.json", "config.toml", "checkpoint.msgpack", "learning_curve.csv", "summary.json"):
        assert (run / name).is_file(), name
    cfg = json.loads((run / "config.json").read_text())
    tree = cfg["config"]
    assert tree["plant"]["n_points"] == 21 and tree["plant"]["delay"] == 0.5 and tree["ppo"]["num_envs"] == 4
    assert cfg["jax_version"] == jax.__version__ and cfg["horizon_steps"] == 30 and cfg["version"] == CONFIG_VERSION
    loaded = load_config(run)  # the one loader (resume, load_policy, evaluation) reads the tree back
    assert loaded.plant.n_points == 21 and loaded.ppo.num_envs == 4 and loaded.run.max_wall_s == float("inf")
    assert loaded.env == TrainConfig.make(env={k: tuple(v) if isinstance(v, list) else v
                                               for k, v in tree["env"].items()}).env
    rows = _rows(run)
    assert list(rows[0]) == CURVE_FIELDS
    assert [int(r["env_steps"]) for r in rows] == [CHUNK, 2 * CHUNK, 3 * CHUNK, 4 * CHUNK]
    assert [int(r["update"]) for r in rows] == [2, 4, 6, 8]
    assert all(np.isfinite(float(r[k])) for r in rows for k in CURVE_FIELDS)
    summary = json.loads((run / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(summary)
    assert summary["env_steps"] == 4 * CHUNK and summary["wall_s"] > 0 and summary["interrupted"] is False
    assert summary["eval_horizon_s"] == 2.0 and summary["target_reward"] == -0.1
    fe = summary["final_eval"]
    for k in ("final_reward", "J_comfort", "final_rho_L2", "final_v_L2", "J_TTT", "J_fuel"):
        assert len(fe[k]) == 1 and np.isfinite(fe[k][0]), k
    assert fe["final_reward"][0] == pytest.approx(float(rows[-1]["eval_reward"]))
    if summary["stop_rule_reached"]:
        assert summary["seconds_to_stop_rule"] > 0
    else:
        assert summary["seconds_to_stop_rule"] is None
    try:
        from jaxtraffic.paper.plotting import plot_learning_curve  # noqa: F401
    except ImportError:
        pytest.skip("jaxtraffic.plotting.plot_learning_curve not available yet: learning_curve.png not checked")
    png = run / "learning_curve.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_shared_program(runs):
    assert runs["compiled_programs"] == 1  # every run above had the same config (sanity of this module)


def test_resume_is_bit_identical(runs):
    a, b = runs["A"], runs["B"]
    assert len(runs["B_first_rows"]) == 2 and runs["B_first_summary"]["env_steps"] == 2 * CHUNK
    assert _no_wall(_rows(b)) == _no_wall(_rows(a))
    state_a, meta_a = ckpt.load_checkpoint(a)
    state_b, meta_b = ckpt.load_checkpoint(b)
    assert leaves_equal(state_a, state_b)  # params, Adam state, environments, obs statistics, keys
    assert leaves_equal(ckpt.load_best(a), ckpt.load_best(b))  # the kept best checkpoints too
    assert meta_a["env_steps"] == meta_b["env_steps"] == 4 * CHUNK
    sa, sb = (json.loads((r / "summary.json").read_text()) for r in (a, b))
    assert sa["final_eval"] == sb["final_eval"] and sa["env_steps"] == sb["env_steps"]


def test_random_restarts_reinitialise_and_resume_exactly(runs):
    """Run R never meets its rule: every 2 chunks (``--restart-steps``) its member is re-initialised
    from a new key (the observation statistics start afresh, the learning curve jumps), not at the
    run's last chunk; the same run interrupted after 3 chunks and resumed restarts at the same steps
    and ends bit-identical (checkpoint, best checkpoint, curve)."""
    r, half = runs["R"], runs["R_half"]
    summary = json.loads((r / "summary.json").read_text())
    assert summary["restarts"] == [{"env_steps": 2 * CHUNK, "members": [0]}, {"env_steps": 4 * CHUNK, "members": [0]}]
    assert [int(row["restarts"]) for row in _rows(r)] == [0, 1, 1, 2, 2, 2]
    state_r, meta_r = ckpt.load_checkpoint(r)
    state_h, meta_h = ckpt.load_checkpoint(half)
    assert leaves_equal(state_r, state_h) and leaves_equal(ckpt.load_best(r), ckpt.load_best(half))
    assert _no_wall(_rows(r)) == _no_wall(_rows(half)) and meta_r["restarts"] == meta_h["restarts"]
    assert meta_r["member_start_steps"] == [4 * CHUNK]
    assert int(np.asarray(state_r["update"]).max()) == 2 * 2  # 2 chunks x 2 updates since the last restart


def test_ctrl_c_saves_and_resume_loses_nothing(runs):
    a, i = runs["A"], runs["I"]
    first = runs["I_first_summary"]
    assert first["interrupted"] is True and first["env_steps"] == 2 * CHUNK
    # written on the way out: by the interval (--checkpoint-every 10) only chunk 1's would be on disk
    assert ckpt.load_checkpoint(i.parent / "I_first")[1]["env_steps"] == 2 * CHUNK
    assert _no_wall(runs["I_first_rows"]) == _no_wall(_rows(a))[:2]
    assert _no_wall(_rows(i)) == _no_wall(_rows(a))
    assert leaves_equal(ckpt.load_checkpoint(a)[0], ckpt.load_checkpoint(i)[0])


def test_same_seed_same_curve_different_seed_differs(runs):
    a_rows = _no_wall(_rows(runs["A"]))
    assert _no_wall(runs["B_first_rows"]) == a_rows[:2]  # a fresh run with the same seed
    c_rows = _no_wall(_rows(runs["C"]))
    assert len(c_rows) == 1
    for k in ("mean_reward", "eval_reward", "eta1", "value_loss"):
        assert c_rows[0][k] != a_rows[0][k], k
    pa = ckpt.load_checkpoint(runs["A"])[0]["params"]
    pc = ckpt.load_checkpoint(runs["C"])[0]["params"]
    assert not any(np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(pa), jax.tree_util.tree_leaves(pc),
                                                         strict=True) if np.size(x) > 3)


def test_stop_rule_with_patience(runs):
    rows = _rows(runs["S"])
    summary = json.loads((runs["S"] / "summary.json").read_text())
    assert len(rows) == 2  # met at every evaluation; patience 2 -> stops after the second chunk
    assert summary["stop_rule_reached"] is True and summary["env_steps_to_stop_rule"] == CHUNK
    assert summary["seconds_to_stop_rule"] == pytest.approx(float(rows[0]["wall_s"]), abs=1e-3)


def test_stop_rule_with_wave_speed(runs):
    """--min-wave-speed adds a condition to the paper's rule: the paper's rule alone is still timed."""
    rows = _rows(runs["W"])
    summary = json.loads((runs["W"] / "summary.json").read_text())
    assert len(rows) == 3 and summary["stop_rule_reached"] is False and summary["seconds_to_stop_rule"] is None
    assert summary["min_wave_speed"] == 1e9
    assert summary["seconds_to_paper_rule"] == pytest.approx(float(rows[0]["wall_s"]), abs=1e-3)
    assert summary["env_steps_to_paper_rule"] == CHUNK
    s = summary["final_eval"]["wave_speed"]
    assert len(s) == 1 and np.isfinite(s[0]) and len(summary["final_eval"]["equilibrium_gains"][0]) == 3
    assert float(rows[-1]["eval_wave_speed"]) == pytest.approx(s[0], rel=1e-6)
    plain = json.loads((runs["S"] / "summary.json").read_text())
    assert plain["min_wave_speed"] is None and plain["seconds_to_paper_rule"] == plain["seconds_to_stop_rule"]


def test_checkpoint_round_trip_gives_identical_actions(runs):
    rt = runs["roundtrip"]
    assert rt["identical"] == [True, True]  # load_policy(run) == in-memory policy, bit for bit
    assert rt["stats_trained"]  # the observation statistics were part of the round trip, not defaults
    assert not np.allclose(rt["h"][0], rt["h"][1])  # the actions depend on the state
    assert rt["bad_seed_rejected"]


def test_load_policy_loads_the_best_checkpoint(runs):
    """By default ``load_policy`` returns the best-scoring checkpoint that the trainer kept
    (best.msgpack), whose score and step match the learning curve."""
    run = runs["A"]
    summary = json.loads((run / "summary.json").read_text())
    best = ckpt.load_best(run)
    rows = _rows(run)
    scores = [float(r["val_score"]) for r in rows]
    assert summary["best_val_score"][0] == pytest.approx(min(scores)) == pytest.approx(float(best["score"][0]))
    assert summary["best_env_steps"][0] == int(rows[int(np.argmin(scores))]["env_steps"])
    ctrl, _ = load_policy(run)
    assert leaves_equal(ctrl.settings.params, jax.tree.map(lambda x: x[0], best["params"]))
    np.testing.assert_array_equal(ctrl.settings.obs_mean, best["mean"][0])
    assert float(rows[-1]["best_val_score"]) == pytest.approx(min(scores))
    with pytest.raises(ValueError, match="checkpoint"):
        load_policy(run, checkpoint="first")


def test_validation_scores_the_candidates(runs):
    """Run S meets the paper's rule at every evaluation: each checkpoint is validated (a finite score
    below the unvalidated rank) and the summary records the suite (delays at the ends and the middle of
    the training range)."""
    summary = json.loads((runs["S"] / "summary.json").read_text())
    val = summary["validation"]
    assert val["delays"] == [0.0, 0.5, 1.5] and val["horizon_s"] == 2.0 and val["target"] is None  # inf
    assert len(val["reference"]["labels"]) == 6
    assert all(float(r["val_score"]) < 1e7 for r in _rows(runs["S"]))
    assert load_config(runs["S"]).run.val_target == float("inf")


def test_load_policy_rejects_a_run_from_an_older_version(runs, tmp_path):
    """A config.json of a layout before the config tree (flat "settings", an "algo" section) is a clear error,
    not a run loaded with guessed values; one of today's layout without a field loads it at its default."""
    old = tmp_path / "old"
    shutil.copytree(runs["A"], old)
    data = json.loads((old / "config.json").read_text())
    tree = data["config"]
    flat = {k: v for section in tree.values() for k, v in section.items()}
    renamed = {"algo": tree["ppo"], **{k: v for k, v in tree.items() if k != "ppo"}}
    for written in ({"settings": flat}, {"config": renamed}):
        (old / "config.json").write_text(json.dumps({**{k: v for k, v in data.items() if k != "config"}, **written}))
        with pytest.raises(ValueError, match="which this jaxtraffic cannot read"):
            load_policy(old)
    lacking = {**tree, "env": {k: v for k, v in tree["env"].items() if k != "wave_weight"}}
    (old / "config.json").write_text(json.dumps({**data, "config": lacking}))
    assert load_policy(old)[1] == load_config(runs["A"])
    load_policy(runs["A"])  # the unmodified run loads


@pytest.mark.parametrize("algo", ["ppo", "gradient"])
def test_cli_help_documents_every_flag(algo, capsys):
    """Each subcommand's help lists the flags of the fields its algorithm reads (``-H``: with their help), and
    no flag of the other's."""
    from jaxtraffic.runs.config.tree import fields_for

    with pytest.raises(SystemExit) as exc:
        train_cli.main([algo, "-H"])  # (the same as --help)
    assert exc.value.code == 0
    text = capsys.readouterr().out
    other = "gradient" if algo == "ppo" else "ppo"
    mine = {f.name for _, f in fields_for(algo)}
    for _, f in fields_for(algo):
        assert f.metadata.get("help"), f"{f.name} has no help"
        flag = ("--no-" if f.default is True else "--") + f.name.replace("_", "-")
        assert flag in text
    for _, f in fields_for(other):
        if f.name not in mine:
            assert f"--{f.name.replace('_', '-')} " not in text
    for flag in ("--delay", "--n-points", "--out-dir", "--resume", "--max-wall-s", "--config", "--hidden",
                 *(("--num-envs", "--total-steps", "--num-seeds", "--lr", "--delay-range") if algo == "ppo"
                   else ("--policy", "--grad-steps", "--train-delays", "--grad-lr"))):
        assert flag in text


def test_cli_help_describes_every_flag_by_section_and_the_subcommand_is_optional(capsys):
    """``--help`` (not only -H): every flag with its one-line description, grouped by config section; a boolean
    on by default shows both forms."""
    from jaxtraffic.runs.config.tree import fields_for

    for algo in ("ppo", "gradient"):
        with pytest.raises(SystemExit):
            train_cli.main([algo, "--help"])
        text = " ".join(capsys.readouterr().out.replace("│", " ").split())
        assert len(text) < 12_000
        sections = [s for s in ("plant", "env", "ppo", "grad", "run") if f" {s} options " in text]
        assert sections == (["plant", "env", "ppo", "run"] if algo == "ppo" else ["plant", "env", "ppo", "grad", "run"])
        for _, f in fields_for(algo):
            assert " ".join(f.metadata["help"].split()) in text, f.name
        assert ("--require-certificate, --no-require-certificate" in text) == (algo == "ppo")
    assert train_cli.config_from_args(["--delay", "3"]) == train_cli.config_from_args(["ppo", "--delay", "3"])
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("train.py ")


@pytest.mark.parametrize("argv, match", [
    (["--algo", "gradient"], "--algo was removed; use `train.py gradient`"),
    (["--seeds", "2"], "--seeds was removed; use --num-seeds"),
    (["--num-seed", "2"], "unrecognized arguments: --num-seed"),  # no abbreviations
    (["--n-point", "21"], "unrecognized arguments: --n-point"),
    (["--grad-steps", "2"], "--grad-steps: a flag of `train.py gradient`, not of `train.py ppo`"),
    (["gradient", "--lr", "0.1"], "--lr: a flag of `train.py ppo`, not of `train.py gradient`"),
    (["--scheme", "weno"], "--scheme: invalid choice 'weno'"),
])
def test_cli_refuses_in_one_line(argv, match, capsys):
    with pytest.raises(SystemExit) as exc:
        train_cli.main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and match in err and err.count("\n") == 1, err


def test_cli_values_and_their_defaults():
    c = train_cli.config_from_args
    assert c([]) == TrainConfig()
    assert c(["--hidden", "32,16"]).ppo.hidden == c(["--hidden", "32", "16"]).ppo.hidden == (32, 16)
    assert c(["--min-wave-speed", "-inf"]).run.min_wave_speed is None
    assert c(["--no-require-certificate"]).run.require_certificate is False
    g = c(["gradient", "--policy", "schedule", "--train-delays", "1", "2"])
    assert g.run.out_dir == "runs/gradient-schedule" and g.grad.train_delays == (1.0, 2.0)
    assert g.grad.grad_method == "cem"  # the policy's defaults under the flags given


@pytest.mark.parametrize("argv, match", [
    (["--delay", "0.05", "--dt", "0.1"], "multiple of dt"),
    (["--alpha", "1.5"], "alpha"),
    (["--alpha-range", "0.1,1.5"], "alpha_range"),
    (["--delay-range", "3,2"], "delay_range"),
    (["--n-points", "2"], "n_points"),
    (["--hidden", "a"], "--hidden"),
    (["--delay-range", "1"], "--delay-range"),
    (["--clip-eps", "0"], "clip_eps"),
    (["--diverge-penalty", "-1"], "diverge_penalty"),
])
def test_cli_invalid_values_exit_2(argv, match, tmp_path, capsys):
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        train_cli.main(argv + ["--out-dir", str(out), "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err
    assert not out.exists()  # rejected before anything is written


def test_diverge_penalty_flag_reaches_the_environment():
    """--diverge-penalty sets EnvParams.diverge_penalty (the reward of a diverging step); default 100."""
    from jaxtraffic.runs.ppo.trainer import build

    assert float(build(train_cli.config_from_args([]))[1].diverge_penalty) == 100.0
    assert float(build(train_cli.config_from_args(["--diverge-penalty", "2e4"]))[1].diverge_penalty) == 2e4


def test_cli_invalid_value_from_the_shell(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), "--delay", "0.05", "--out-dir", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert proc.returncode == 2, proc.stderr
    assert "train.py: error:" in proc.stderr and "delay" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()


@pytest.mark.slow  # end to end (seconds to tens of seconds): CI's slow tier
def test_two_cpu_devices(two_device_proc):
    try:
        stdout, stderr = two_device_proc.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        two_device_proc.kill()
        raise
    assert two_device_proc.returncode == 0, stderr[-3000:]
    line = [x for x in stdout.splitlines() if x.startswith("RESULT ")]
    assert line, stdout[-2000:]
    res = json.loads(line[0][len("RESULT "):])
    assert res["device_count"] == 2
    assert res["leading_axis"] == [2, 2, 2]
    assert res["params_replicated"] and res["stats_replicated"]  # lax.pmean keeps the devices in step
    assert res["envs_differ"]  # each device runs its own environments
    assert res["env_steps"] == 3 * CHUNK and res["n_rows"] == 3 and res["finite"]
    assert np.isfinite(res["final_reward"][0])


def test_population_run(tmp_path):
    """The default is a population (``config.POPULATION`` members in one jit): every member is
    evaluated, the best one is the run's policy, and the members are different policies."""
    from jaxtraffic.runs.config import POPULATION

    assert TrainConfig().ppo.num_seeds == POPULATION == 2
    argv = list(TINY)
    argv[argv.index("--num-seeds") + 1] = "2"
    run = train_cli.main(argv + ["--out-dir", str(tmp_path / "pop"), "--keep-going", "--total-steps", str(2 * CHUNK),
                                 "--val-horizon-s", "0"])
    summary = json.loads((run / "summary.json").read_text())
    assert summary["env_steps"] == 2 * CHUNK  # per member
    fe = summary["final_eval"]
    assert len(fe["final_reward"]) == 2 and np.all(np.isfinite(fe["final_reward"]))
    assert fe["final_reward"][0] != fe["final_reward"][1]  # two different networks
    best = summary["best_seed"]
    assert best == int(np.argmin(summary["best_val_score"])) and best in (0, 1)
    _, cfg = load_policy(run)
    assert cfg.ppo.num_seeds == 2
