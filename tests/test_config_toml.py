"""A run's config.toml: the full config, read back as it was written, and a run started from it
(``train.py --config run/config.toml``) reproduces the original bit for bit."""

from __future__ import annotations

import math

import pytest
from flax import serialization
from tiny_runs import TINY

import jaxtraffic
from jaxtraffic.cli import train as train_cli
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import TrainConfig, load_config
from jaxtraffic.runs.config.toml import read_config, write_config
from jaxtraffic.runs.config.tree import CONFIG_VERSION

GRAD = ["gradient", "--policy", "schedule", "--n-points", "21", "--train-delays", "1", "--train-alphas",
        "0.15", "--train-horizon-s", "2", "--steps-per-chunk", "1", "--grad-steps", "2", "--eval-horizon-s", "2",
        "--quiet"]


def _trained(run) -> bytes:
    outer = serialization.msgpack_restore((run / ckpt.CHECKPOINT).read_bytes())
    payload = serialization.msgpack_restore(outer["payload"])
    return serialization.msgpack_serialize({k: v for k, v in payload.items() if k != "meta"})


def test_toml_round_trip(tmp_path):
    config = TrainConfig.make(run={"algo": "gradient", "min_wave_speed": None, "max_wall_s": math.inf},
                              grad={"policy": "network"}, env={"delay_range": (1.0, 2.0)},
                              ppo={"num_seeds": 3, "hidden": (8, 8)})
    write_config(config, tmp_path / "c.toml")
    assert read_config(tmp_path / "c.toml") == config
    (tmp_path / "bad.toml").write_text("[ppo]\nclip_epss = 0.1\n")
    with pytest.raises(ValueError, match="has no field 'clip_epss'"):
        read_config(tmp_path / "bad.toml")


def test_the_plant_section_is_traffic_params_and_a_file_sets_its_physics(tmp_path):
    """The plant section is the library's TrafficParams as it is: a config file sets any of its fields (the
    road's length, the inflow...), which reach the environment; only the ones with a help text are flags."""
    (tmp_path / "road.toml").write_text("[plant]\nL = 2000.0\nq_in = 0.3\nn_points = 401\n")
    config = read_config(tmp_path / "road.toml")
    assert isinstance(config.plant, jaxtraffic.TrafficParams)
    assert config.env_params().traffic == jaxtraffic.TrafficParams(delay=4.0, L=2000.0, q_in=0.3, n_points=401)
    assert train_cli.config_from_args(["--config", str(tmp_path / "road.toml"), "--delay", "2"]).plant.L == 2000.0
    with pytest.raises(SystemExit):  # a physical constant is a config file's, not a flag
        train_cli.main(["--L", "2000"])
    with pytest.raises(ValueError, match=r"q_in = 'fast': must be a number"):
        TrainConfig.make(plant={"q_in": "fast"})


def test_a_version_3_config_json_is_converted():
    """Version 3 held eight of the plant's fields (the others could not be set: they were the defaults), and the
    controller's own grid in the environment's section (None: the plant's), and (to version 4) the initial
    amplitudes in veh/m."""
    from jaxtraffic.runs.config import config_from_json, config_json
    from jaxtraffic.runs.config.tree import fields_for

    config = TrainConfig.make(plant={"n_points": 21, "delay": 2.0}, run={"seed": 7, "algo": "gradient"},
                              grad={"controller_points": 11})
    data = config_json(config)
    flags = {f.name for s, f in fields_for("ppo") if s == "plant"}
    assert flags == {"delay", "alpha", "alpha_noise", "n_points", "scheme", "substeps", "dt", "max_delay_steps"}
    tree = data["config"]
    old = {**data, "version": 3, "config": {
        **tree, "plant": {k: v for k, v in tree["plant"].items() if k in flags},
        "env": {**tree["env"], "controller_points": 11, "amp_range": (0.01, 0.01)},
        "grad": {**{k: v for k, v in tree["grad"].items() if k != "controller_points"}, "train_amplitudes": (0.01,)}}}
    assert config_from_json(old) == config
    ppo = config_json(TrainConfig.make(plant={"n_points": 21}))
    old_ppo = {**ppo, "version": 3,
               "config": {**ppo["config"], "env": {**ppo["config"]["env"], "controller_points": None,
                                                   "amp_range": (0.01, 0.01)}}}
    assert config_from_json(old_ppo).grad.controller_points == 0
    # a version-4 file without the plant's other fields (written before they existed): at their defaults
    assert config_from_json({**old, "version": 4}).plant.L == TrainConfig().plant.L


@pytest.mark.parametrize("argv", [[*TINY, "--total-steps", "64", "--keep-going"], GRAD], ids=["ppo", "gradient"])
def test_a_run_from_its_config_toml_is_the_same_run(argv, tmp_path):
    first = train_cli.main([*argv, "--out-dir", str(tmp_path / "a")])
    again = train_cli.main(["--config", str(first / "config.toml"), "--out-dir", str(tmp_path / "b")])
    assert load_config(again).updated(run={"out_dir": "x"}) == load_config(first).updated(run={"out_dir": "x"})
    assert _trained(again) == _trained(first)  # every saved array, byte for byte (the meta holds wall times)
    # the file's algorithm selects the subcommand; a flag given with --config overrides the file
    over = train_cli.config_from_args(["--config", str(first / "config.toml"), "--seed", "5"])
    assert over.run.seed == 5 and over.updated(run={"seed": 0}) == load_config(first).updated(run={"seed": 0})
    algo = load_config(first).run.algo
    assert train_cli.config_from_args([algo, "--config", str(first / "config.toml")]) == load_config(first)
    with pytest.raises(SystemExit):  # (here: a bad value)
        train_cli.main(["--config", str(first / "config.toml"), "--out-dir", str(tmp_path / "c"), "--seed", "-1"])


def test_removed_flags_name_their_replacement_and_version(capsys):
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--network", "paper"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--network was removed; use --hidden" in err and err.count("\n") == 1
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--version"])
    out = capsys.readouterr().out.split()
    assert exc.value.code == 0 and out == [train_cli.PROG, jaxtraffic.__version__]  # the one place it is written
    with pytest.raises(SystemExit):  # no abbreviations: --clip is not --clip-eps
        train_cli.main(["--clip", "0.1"])
    assert "unrecognized arguments: --clip" in capsys.readouterr().err


def test_sections_and_flags_map_to_fields_and_unknown_names_are_refused():
    """``make``/``updated`` take one mapping per section; flag names map to their sections (``flag_tables``), the
    same mapping the Gymnasium environment's keywords go through."""
    from jaxtraffic.ecosystem import resolve_env_params
    from jaxtraffic.runs.config.tree import flag_tables

    assert flag_tables("ppo", {"n_points": 21, "lr": 0.5, "seed": 2}) == {
        "plant": {"n_points": 21}, "ppo": {"lr": 0.5}, "run": {"seed": 2}}
    with pytest.raises(TypeError, match="'grad_lr' is not a field of train.py ppo's flags"):
        flag_tables("ppo", {"grad_lr": 0.1})
    with pytest.raises(TypeError, match="unknown config section 'algo'"):
        TrainConfig.make(algo={"lr": 0.5})
    with pytest.raises(TypeError, match="section 'ppo' has no field 'n_points'"):
        TrainConfig.make(ppo={"n_points": 21})
    with pytest.raises(TypeError, match="unknown config section 'plants'"):
        TrainConfig().updated(plants={"n_points": 21})
    assert TrainConfig().updated(ppo={"lr": 0.5}) == TrainConfig.make(ppo={"lr": 0.5})
    assert resolve_env_params(n_points=21, horizon_s=1.0).horizon == 10
    with pytest.raises(TypeError, match="unknown environment config field"):
        resolve_env_params(n_pionts=21)


def test_a_saved_config_holds_what_differs_from_the_defaults_and_each_recipe_is_short():
    from importlib import resources

    from jaxtraffic.paper.recipes import NAMES
    from jaxtraffic.runs.config.toml import config_toml

    body = [line for line in config_toml(TrainConfig()).splitlines() if line and not line.startswith("#")]
    assert body == [f"config_version = {CONFIG_VERSION}", "[run]", 'algo = "ppo"']
    lr = config_toml(TrainConfig.make(ppo={"lr": 0.5}, run={"min_wave_speed": None}))
    assert "[ppo]\nlr = 0.5\n" in lr and "min_wave_speed = -inf" in lr and "[env]" not in lr
    for name in NAMES:
        lines = resources.files("jaxtraffic.paper.recipes").joinpath(f"{name}.toml").read_text().splitlines()
        assert len(lines) <= 25, name


def test_an_edited_config_toml_is_honoured_in_its_run_control_and_refused_elsewhere(tmp_path, capsys):
    """A run's config.toml is its truth: ``--resume`` and ``load_policy`` read it; an edit of the run control
    (here the gradient trainer's step count) applies, any other edit is refused in one line naming the field."""
    from jaxtraffic.io.files import read_json
    from jaxtraffic.runs import load_policy
    from jaxtraffic.runs.config import config_from_json

    run = train_cli.main([*GRAD, "--out-dir", str(tmp_path / "r")])
    toml = run / "config.toml"
    assert "grad_steps = 2\n" in toml.read_text()
    toml.write_text(toml.read_text().replace("grad_steps = 2\n", "grad_steps = 3\n"))
    assert load_config(run).grad.grad_steps == 3
    train_cli.main(["--resume", "--out-dir", str(run)])
    assert read_json(run / "summary.json")["updates"] == 3  # trained on to the edited length
    assert config_from_json(read_json(run / "config.json")).grad.grad_steps == 3  # and recorded in the machine copy
    capsys.readouterr()
    toml.write_text(toml.read_text().replace("train_horizon_s = 2.0\n", "train_horizon_s = 3.0\n"))
    before = (run / ckpt.CHECKPOINT).read_bytes()
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--resume", "--out-dir", str(run)])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "[grad] train_horizon_s = 3.0" in err and "2.0" in err
    assert (run / ckpt.CHECKPOINT).read_bytes() == before
    with pytest.raises(ValueError, match=r"config.toml: \[grad\] train_horizon_s = 3.0, but"):
        load_policy(run)


def test_an_older_run_loads_with_its_missing_fields_at_their_defaults(tmp_path):
    """A run written by an older version (tests/data/run_before_config_version: the gradient-gains run as
    docs/results held it before config_version, its config.toml with every field; here also with fields removed as
    if written before they existed) loads as today's run of the same recipe; a version-3 file is migrated; a
    version this jaxtraffic does not know is refused."""
    import shutil
    from pathlib import Path

    from jaxtraffic.io.files import read_json, write_json

    committed = Path(__file__).parents[1] / "docs/results/runs/grad_gains"
    old = Path(__file__).parent / "data/run_before_config_version"
    run = tmp_path / "old"
    run.mkdir()
    for name in ("config.toml", "config.json"):
        shutil.copy(old / name, run / name)
    data = read_json(run / "config.json")
    del data["config"]["env"]["wave_weight"], data["config"]["grad"]["cem_tie_weight"]
    write_json(run / "config.json", data)
    text = (run / "config.toml").read_text()
    assert "config_version" not in text
    (run / "config.toml").write_text("".join(line for line in text.splitlines(keepends=True)
                                             if not line.startswith(("wave_weight =", "cem_tie_weight ="))))
    assert load_config(run) == load_config(committed)
    (tmp_path / "v3.toml").write_text("config_version = 3\n[env]\ncontroller_points = 11\n[plant]\nn_points = 21\n"
                                      "[run]\nalgo = 'gradient'\n")
    assert read_config(tmp_path / "v3.toml").grad.controller_points == 11
    # version 4 gave the initial amplitudes in veh/m; today's are in veh/km (the same waves)
    (tmp_path / "v4.toml").write_text("config_version = 4\n[env]\namp_range = [0.005, 0.015]\n[grad]\n"
                                      "train_amplitudes = [0.01, 0.012]\n[run]\nalgo = 'gradient'\n")
    v4 = read_config(tmp_path / "v4.toml")
    assert v4.env.amp_range == (5.0, 15.0) and v4.grad.train_amplitudes == (10.0, 12.0)
    assert read_config(tmp_path / "v4.toml") == TrainConfig.make(env={"amp_range": (5.0, 15.0)}, grad={
        "train_amplitudes": (10.0, 12.0)}, run={"algo": "gradient"})
    # version 5 held the training sensor noise in [grad]; today's is the environment's (PPO sees it too)
    (tmp_path / "v5.toml").write_text("config_version = 5\n[env]\ntrain_split = 4\n[grad]\n"
                                      "train_sensor_noise = [0.0, 0.05]\n[run]\nalgo = 'gradient'\n")
    v5 = read_config(tmp_path / "v5.toml")
    assert v5.env.train_sensor_noise == v5.grad.train_sensor_noise == (0.0, 0.05)
    (tmp_path / "v5.toml").write_text("config_version = 5\n[grad]\ntrain_sensor_noise = [0.0, 0.05]\n[run]\n"
                                      "algo = 'ppo'\n")  # PPO trained without it, whatever [grad] said
    assert read_config(tmp_path / "v5.toml").env.train_sensor_noise == (0.0, 0.0)
    with pytest.raises(ValueError, match="train_sensor_noise.*needs --train-split"):  # the levels are the split's
        TrainConfig.make(env={"train_sensor_noise": (0.0, 0.05)})
    (tmp_path / "v9.toml").write_text("config_version = 9\n")
    with pytest.raises(ValueError, match=f"config version 9; this jaxtraffic reads versions 3 to {CONFIG_VERSION}"):
        read_config(tmp_path / "v9.toml")


def test_a_checkpoint_bound_to_a_version_4_problem_still_belongs_to_its_migrated_config(tmp_path):
    """A checkpoint stores the problem it was trained on (``checkpoint.problem_of``); one written by version 4 (no
    version in it, the amplitudes in veh/m) belongs to its config read today (veh/km), and a different wave does
    not."""
    import json

    from jaxtraffic.runs.checkpoint import check_problem, problem_of

    def v4(amp: float) -> str:  # today's problem as version 4 wrote it
        problem = json.loads(problem_of(TrainConfig()))
        del problem["config_version"]
        problem["env"]["amp_range"] = [amp, amp]
        problem["grad"]["train_amplitudes"] = [amp]
        return json.dumps(problem, sort_keys=True)

    check_problem(TrainConfig(), v4(0.01), tmp_path / "checkpoint.msgpack")  # 0.01 veh/m: today's 10 veh/km
    check_problem(TrainConfig(), problem_of(TrainConfig()), tmp_path / "checkpoint.msgpack")
    with pytest.raises(ValueError, match=r"env.amp_range = \[10.0, 10.0\], grad.train_amplitudes = \[10.0\], but "
                                         r"checkpoint.msgpack was trained with \[20.0, 20.0\], \[20.0\]"):
        check_problem(TrainConfig(), v4(0.02), tmp_path / "checkpoint.msgpack")
