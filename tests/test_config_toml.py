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
    controller's own grid in the environment's section (None: the plant's)."""
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
        "env": {**tree["env"], "controller_points": 11},
        "grad": {k: v for k, v in tree["grad"].items() if k != "controller_points"}}}
    assert config_from_json(old) == config
    ppo = config_json(TrainConfig.make(plant={"n_points": 21}))
    old_ppo = {**ppo, "version": 3,
               "config": {**ppo["config"], "env": {**ppo["config"]["env"], "controller_points": None}}}
    assert config_from_json(old_ppo).grad.controller_points == 0
    with pytest.raises(ValueError, match=r"older jaxtraffic \(its \[plant\] lacks L"):
        config_from_json({**old, "version": 4})


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
