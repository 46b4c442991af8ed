"""Issue 28's hostile-user cases, rerun: each one a command (or a few), its exit status and first error line.

    python benchmarks/hostile_cases.py [--only 1,4] [--json]

Every case runs in a fresh subprocess on a tiny problem (21 points) in a temporary directory and prints one
row: the case, what was run, the exit status, whether a traceback appeared, the first line of stderr, and
whether that is what the case expects. Exit status 1 if any case does not behave as expected. BENCHMARKS.md
("Reliability, round two") holds a run of it.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TINY = ["--n-points", "21", "--num-envs", "4", "--num-steps", "8", "--updates-per-chunk", "2", "--num-minibatches",
        "2", "--horizon-s", "3", "--eval-horizon-s", "2", "--val-horizon-s", "2", "--delay", "0.5",
        "--max-delay-steps", "20", "--keep-going", "--quiet"]
GRAD = ["gradient", "--policy", "gains", "--n-points", "21", "--train-delays", "1", "--train-horizon-s",
        "2", "--steps-per-chunk", "1", "--eval-horizon-s", "2", "--quiet"]
LOAD = ("import sys; from jaxtraffic.runs import load_policy\ntry:\n    load_policy('{run}')\n"
        "except ValueError as e:\n    sys.exit(f'load_policy: {{e}}')")  # a library error: one line, exit 1
SUMMARY = "import json; print('{key}', json.load(open('{run}/summary.json'))['{key}'])"
TRACED = ("import jax, jax.numpy as jnp, jaxtraffic as jt; p = jt.TrafficParams(n_points=21, max_delay_steps=100); "
          "f = jax.jit(lambda x: jt.simulate(p.replace({f}=x), {ctrl}, n_steps=5).metrics['diverged_reason']); "
          "print('diverged_reason', int(f(jnp.float32({v}))))")


def _run(argv: list[str], cwd: Path, env: dict | None = None, stdin_close_after: int | None = None,
         signal_on: tuple[str, int] | None = None, timeout: float = 300) -> tuple[int, str, str]:
    """Run ``python argv`` in ``cwd``: (exit status, stdout, stderr). ``signal_on = (text, sig)``: send ``sig``
    when a stdout line contains ``text`` ("" : after 0.3 s); ``stdin_close_after``: close stdout after that many
    lines (a reader that quits, like ``head``)."""
    proc = subprocess.Popen([sys.executable, *argv], cwd=cwd, env={**os.environ, **(env or {})},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out = []
    if signal_on is not None and signal_on[0] == "":
        time.sleep(0.3)
        proc.send_signal(signal_on[1])
    elif signal_on is not None or stdin_close_after is not None:
        for line in proc.stdout:
            out.append(line)
            if signal_on is not None and signal_on[0] in line:
                proc.send_signal(signal_on[1])
                break
            if stdin_close_after is not None and len(out) >= stdin_close_after:
                proc.stdout.close()
                break
    try:
        rest, err = proc.communicate(timeout=timeout)
    except ValueError:  # stdout closed by us
        err = proc.stderr.read()
        proc.wait(timeout=timeout)
        rest = ""
    return proc.returncode, "".join(out) + (rest or ""), err


def _mount(where: Path) -> None:
    where.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(where)]).returncode:
        raise RuntimeError("needs root and mount")


def cases(tmp: Path) -> list[tuple[str, str, list, dict, int, str]]:
    """(id, description, steps, run options, expected exit status, expected text in stderr or stdout)."""
    T = [str(REPO / "train.py"), *TINY]
    E = [str(REPO / "evaluate.py")]
    r = lambda name: ["--out-dir", str(tmp / name)]  # noqa: E731
    cfg = tmp / "ed" / "config.json"
    return [
        ("1", "fresh run into another run's directory", [T + ["--total-steps", "64"] + r("a"),
                                                         T + ["--lr", "0.5"] + r("a")], {}, 2, "holds a run already"),
        ("1", "... with --overwrite (clears it first)", [T + ["--total-steps", "64"] + r("a2"),
                                                         T + ["--total-steps", "64", "--overwrite"] + r("a2")], {}, 0,
         ""),
        ("2", "--resume alone keeps the run's --total-steps", [T + ["--total-steps", "64"] + r("b"),
                                                               [str(REPO / "train.py"), "--resume"] + r("b"),
                                                               ["-c", SUMMARY.format(key="env_steps", run=tmp / "b")]],
         {}, 0, "env_steps 64"),
        ("2", "gradient --resume --grad-steps 3 runs 3", [[str(REPO / "train.py"), *GRAD, "--grad-steps", "2"] + r("g"),
                                                          [str(REPO / "train.py"), "--resume", "--grad-steps", "3",
                                                           "--quiet"] + r("g"),
                                                          ["-c", SUMMARY.format(key="updates", run=tmp / "g")]],
         {}, 0, "updates 3"),
        ("2", "--resume with a flag that changes the problem", [T + ["--total-steps", "64"] + r("c"),
                                                                [str(REPO / "train.py"), "--resume", "--lr", "0.5"]
                                                                + r("c")], {}, 2, "would change it: --lr 0.5"),
        ("3", "traced plant delay 12 s (buffer 10 s)",
         [["-c", TRACED.format(f="delay", ctrl="jt.lyapunov(1.0)", v=12.0)]], {}, 0, "diverged_reason 4"),
        ("3", "traced plant delay -0.1 s", [["-c", TRACED.format(f="delay", ctrl="jt.lyapunov(1.0)", v=-0.1)]], {}, 0,
         "diverged_reason 4"),
        ("3", "traced alpha -0.5", [["-c", TRACED.format(f="alpha", ctrl="jt.lyapunov(1.0)", v=-0.5)]], {}, 0,
         "diverged_reason 4"),
        ("3", "traced dt -0.1", [["-c", TRACED.format(f="dt", ctrl="jt.lyapunov(1.0)", v=-0.1)]], {}, 0,
         "diverged_reason 4"),
        ("3", "traced backstepping(nan)",
         [["-c", "import jax, jax.numpy as jnp, jaxtraffic as jt; p = jt.TrafficParams(n_points=21); "
                 "print('diverged_reason', int(jax.jit(lambda d: jt.simulate(p, jt.backstepping(d), "
                 "n_steps=5).metrics['diverged_reason'])(jnp.nan)))"]], {}, 0, "diverged_reason 2"),
        ("4", "--lr 1e30 (float32-finite, blows up)", [T + ["--lr", "1e30", "--total-steps", "256"] + r("n")], {}, 2,
         "training went non-finite"),
        ("4", "--lr 1e300", [T + ["--lr", "1e300"] + r("n2")], {}, 2, "must be finite in float32"),
        ("4", "--gain-max 1e300", [T + ["--gain-max", "1e300"] + r("n3")], {}, 2, "must be finite in float32"),
        ("4", "--reward-scale 1e30", [T + ["--reward-scale", "1e30", "--total-steps", "256"] + r("n4")], {}, 2,
         "training went non-finite"),
        ("4", "gradient --train-delays 50", [[str(REPO / "train.py"), *GRAD, "--train-delays", "50"] + r("s1")], {}, 2,
         "beyond the delay buffer"),
        ("4", "gradient --record-every 1000000", [[str(REPO / "train.py"), *GRAD, "--record-every", "1000000"]
                                                  + r("s2")], {}, 2, "must be <= the training horizon"),
        ("4", "gradient --train-amplitudes -1000", [[str(REPO / "train.py"), *GRAD, "--train-amplitudes", "-1000"]
                                                   + r("s3")],
         {}, 2, "leaves the physical region"),
        ("4", "PPO --amp-range 1000,1000", [T + ["--amp-range", "1000,1000"] + r("s4")], {}, 2,
         "leaves the physical region"),
        ("4", "gradient with PPO's --num-envs 7 --tensorboard D", [[str(REPO / "train.py"), *GRAD, "--num-envs", "7",
                                                                   "--tensorboard", "D"] + r("s5")], {}, 2,
         "a flag of `train.py ppo`"),
        ("4", "gradient with PPO's batch rule broken (--num-minibatches 7 in config)",
         [["-c", "from jaxtraffic.runs.config import TrainConfig; TrainConfig.make(run={'algo': 'gradient'}, "
                 "ppo={'num_minibatches': 7}); print('accepted')"]], {}, 0, "accepted"),
        ("5", "evaluate.py SIGINT during the robustness map", [T + ["--total-steps", "64"] + r("e"),
                                                               E + ["--run", str(tmp / "e"), "--out", str(tmp / "eo"),
                                                                    "--horizon", "4", "--noise-seeds", "1",
                                                                    "--robust-grid", "2x2", "--gradient", "none",
                                                                    "--plants", "paper"]],
         {"signal_on": ("robustness map", signal.SIGINT)}, 130, "nothing was written to"),
        ("5", "evaluate.py --robust-grid 1000000x1000000", [E + ["--robust-grid", "1000000x1000000", "--out",
                                                                 str(tmp / "eo2")]], {}, 2, "at most 10000"),
        ("6", "--wavenumber-range 1e12,1e12", [T + ["--wavenumber-range", "1e12,1e12"] + r("o1")], {}, 2, "invalid"),
        ("6", "--horizon-s 1e30", [T + ["--horizon-s", "1e30"] + r("o2")], {}, 2, "must be at most 1e+08 time steps"),
        ("6", "--eval-horizon-s 1e30", [T + ["--eval-horizon-s", "1e30"] + r("o3")], {}, 2, "must be at most 1e+08"),
        ("6", "--max-delay-steps 2147483648", [T + ["--max-delay-steps", "2147483648"] + r("o4")], {}, 2,
         "must lie in [0, 1000000]"),
        ("6", "evaluate.py --horizon 1e30", [E + ["--horizon", "1e30", "--out", str(tmp / "eo3")]], {}, 2,
         "--horizon must be a number of seconds in (0, 1e+07]"),
        ("6", "--num-envs 2147483648", [T + ["--num-envs", "2147483648"] + r("o5")], {}, 2, "must fit int32"),
        ("6", "--num-steps 1000000000", [T + ["--num-steps", "1000000000"] + r("o6")], {}, 2,
         "the rollouts alone need"),
        ("6", "train.py ... | head -1", [[str(REPO / "train.py"), *GRAD[:-1], "--grad-steps", "3"] + r("p")],
         {"stdin_close_after": 1}, 74, "standard output was closed (broken pipe)"),
        ("6", "Ctrl-C while jax is imported", [[str(REPO / "train.py"), "--help"]], {"signal_on": ("", signal.SIGINT)},
         130, ""),
        ("6", "a full disk (a 300 kB tmpfs: root only)",
         [T + ["--total-steps", "64", "--out-dir", str(tmp / "full" / "r")]],
         {"pre": lambda: _mount(tmp / "full"), "post": lambda: subprocess.run(["umount", str(tmp / "full")])}, 74,
         "No space left on device"),
        ("6", "gradient --init-gains 1,2", [[str(REPO / "train.py"), *GRAD, "--init-gains", "1,2"] + r("o7")], {}, 2,
         "must be three gains"),
        ("6", "config.json nested 100 000 deep", [T + ["--total-steps", "64"] + r("q"),
                                                  ["-c", f"open('{tmp / 'q' / 'config.json'}', 'w').write('[' * 100000 "
                                                         "+ ']' * 100000)"],
                                                  E + ["--run", str(tmp / "q"), "--out", str(tmp / "qo")]], {}, 2,
         "unreadable or not valid JSON (RecursionError"),
        ("7", "config.json edited after training (gain_max)", [
            T + ["--total-steps", "64"] + r("ed"),
            ["-c", f"import json; p = '{cfg}'; c = json.load(open(p)); c['config']['env']['gain_max'] = 0.123; "
                   "json.dump(c, open(p, 'w'))"],
            ["-c", LOAD.format(run=tmp / "ed")]], {}, 1, "do not belong together"),
        ("7", "config.json's algo edited to gradient", [
            T + ["--total-steps", "64"] + r("ed2"),
            ["-c", f"import json; p = '{tmp / 'ed2' / 'config.json'}'; c = json.load(open(p)); "
                   "c['config']['run']['algo'] = 'gradient'; json.dump(c, open(p, 'w'))"],
            E + ["--run", str(tmp / "ed2"), "--out", str(tmp / "edo")]], {}, 2, "do not belong together"),
        ("7", "best.msgpack deleted", [T + ["--total-steps", "64"] + r("bd"),
                                       ["-c", f"import os; os.remove('{tmp / 'bd' / 'best.msgpack'}')"],
                                       ["-c", LOAD.format(run=tmp / "bd")]], {}, 1, "best.msgpack is missing"),
        ("7", "evaluate.py --run <gradient run> describes it", [
            [str(REPO / "train.py"), *GRAD, "--grad-steps", "1"] + r("gd"),
            ["-c", "import sys; sys.path.insert(0, '.'); from jaxtraffic.cli.evaluate import _describe; "
                   f"from jaxtraffic.runs.config import load_config; print(_describe('{tmp / 'gd'}', "
                   f"load_config('{tmp / 'gd'}'))['description'])"]], {}, 0, "gradient-trained gains"),
        ("8", "learning_curve.png a symlink to a file outside", [
            T + ["--total-steps", "64"] + r("sl"),
            ["-c", f"import os; open('{tmp / 'precious'}', 'w').write('keep'); "
                   f"os.remove('{tmp / 'sl' / 'learning_curve.png'}'); "
                   f"os.symlink('{tmp / 'precious'}', '{tmp / 'sl' / 'learning_curve.png'}')"],
            [str(REPO / "train.py"), "--resume", "--total-steps", "128"] + r("sl"),
            ["-c", f"print('outside file:', open('{tmp / 'precious'}').read())"]], {}, 0, "outside file: keep"),
        ("8", "a world-writable compilation cache", [T + ["--total-steps", "64"] + r("wc")],
         {"env": {"JAXTRAFFIC_COMPILATION_CACHE": str(tmp / "ww")}, "pre": lambda: (tmp / "ww").mkdir(mode=0o777)
          or os.chmod(tmp / "ww", 0o777)}, 0, "writable by other users"),
        ("8", "SIGHUP during training", [T + ["--total-steps", "100000"] + r("hup")],
         {"signal_on": ("compiling", signal.SIGHUP), "quiet_off": True}, 129, "SIGHUP received"),
        # round three (issue 37): --out only where the job owns, paths checked before the work
        ("9", "evaluate.py --out <a project folder holding runs/>", [
            ["-c", f"import os; os.makedirs('{tmp / 'proj' / 'runs' / 'mine'}'); "
                   f"open('{tmp / 'proj' / 'runs' / 'mine' / 'config.json'}', 'w').write('{{}}'); "
                   f"open('{tmp / 'proj' / 'runs' / 'mine' / 'checkpoint.msgpack'}', 'w').write('')"],
            E + ["--run", str(tmp / "proj" / "runs" / "mine"), "--out", str(tmp / "proj")]], {}, 2,
         "holds no report of evaluate.py's"),
        ("9", "evaluate.py --out ''", [E + ["--out", ""]], {}, 2, "an empty path"),
        ("9", "evaluate.py --out <dangling symlink>", [
            ["-c", f"import os; os.symlink('{tmp / 'nowhere'}', '{tmp / 'dangling'}')"],
            E + ["--out", str(tmp / "dangling")]], {}, 2, "a dangling symbolic link"),
        ("9", "evaluate.py --controller <missing file>", [E + ["--out", str(tmp / "c9"), "--controller",
                                                              f"mine={tmp / 'nope.py'}:make"]], {}, 2,
         "--controller mine: no file"),
        # round four (issue 50): overflows, unbounded reads, config files that do what flags may not
        ("10", "--wavenumber-range 1000000000000 (x2)", [T + ["--wavenumber-range", "1000000000000", "1000000000000"]
                                                        + r("w1")], {}, 2, "must fit int32"),
        ("10", "a wavenumber of 1e9 on 21 points", [T + ["--wavenumber-range", "1000000000", "1000000000"] + r("w2")],
         {}, 2, "Nyquist limit"),
        ("10", "[run] total_steps = 2**63-1 in --config", [
            ["-c", f"open('{tmp / 'ts.toml'}', 'w').write('[run]\\ntotal_steps = 9223372036854775807\\n')"],
            T + ["--config", str(tmp / "ts.toml")] + r("w3")], {}, 2, "must fit int32"),
        ("10", "--config /dev/zero", [T + ["--config", "/dev/zero"] + r("z1")], {}, 2, "a character device"),
        ("10", "--config a FIFO", [["-c", f"import os; os.mkfifo('{tmp / 'fifo.toml'}')"],
                                   T + ["--config", str(tmp / "fifo.toml")] + r("z2")], {}, 2, "a FIFO (named pipe)"),
        ("10", "overwrite = true in a --config file", [
            T + ["--total-steps", "64"] + r("ow"),
            ["-c", f"open('{tmp / 'ow.toml'}', 'w').write('[run]\\noverwrite = true\\n')"],
            T + ["--config", str(tmp / "ow.toml")] + r("ow")], {}, 2, "an action on the run directory"),
        ("10", "hidden = [0] in a --config file", [
            ["-c", f"open('{tmp / 'h.toml'}', 'w').write('[ppo]\\nhidden = [0]\\n')"],
            T + ["--config", str(tmp / "h.toml")] + r("h0")], {}, 2, "h.toml: hidden = 0: must be >= 1"),
        ("10", "config.json version 99, then --resume", [
            T + ["--total-steps", "64"] + r("v9"),
            ["-c", f"import json; p = '{tmp / 'v9' / 'config.json'}'; c = json.load(open(p)); c['version'] = 99; "
                   "json.dump(c, open(p, 'w'))"],
            [str(REPO / "train.py"), "--resume"] + r("v9")], {}, 2, "config version 99"),
        ("10", "adaptive_backstepping(alpha0=5)", [
            ["-c", "import sys; from jaxtraffic.control import adaptive_backstepping as a\ntry:\n    a(alpha0=5)\n"
                   "except ValueError as e:\n    sys.exit(str(e))"]], {}, 1, "alpha0 must lie in [0, 1]"),
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", default="", help="comma-separated case numbers (1-10)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    only = set(filter(None, args.only.split(",")))
    rows, failed = [], 0
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for cid, what, steps, opts, want_rc, want_text in cases(tmp):
            if only and cid not in only:
                continue
            opts = dict(opts)
            post = opts.pop("post", None)
            if "pre" in opts:
                try:
                    opts.pop("pre")()
                except RuntimeError as err:
                    print(f"{cid:>2} --- skipped: {what} ({err})", flush=True)
                    continue
            quiet_off = opts.pop("quiet_off", False)
            t0 = time.perf_counter()
            rc, out, err = 0, "", ""
            for i, argv in enumerate(steps):
                last = i == len(steps) - 1
                if quiet_off:
                    argv = [a for a in argv if a != "--quiet"]
                rc, out, err = _run(argv, REPO, **(opts if last else {k: v for k, v in opts.items() if k == "env"}))
                if not last and rc != 0:
                    break
            if post is not None:
                post()
            text = err + out
            ok = rc == want_rc and want_text in text and "Traceback" not in err
            failed += not ok
            first = next((x for x in err.splitlines() if x.strip() and "Warning" not in x
                          and not x.startswith(" ")), "")
            rows.append({"case": cid, "what": what, "rc": rc, "traceback": "Traceback" in err, "said": first[:160],
                         "expected": f"rc {want_rc}" + (f", '{want_text}'" if want_text else ""), "ok": ok,
                         "s": round(time.perf_counter() - t0, 1)})
            r = rows[-1]
            print(f"{r['case']:>2} {'ok ' if ok else 'BAD'} rc {rc:>3} {r['s']:5.1f} s  {what}: {r['said']}",
                  flush=True)
    if args.json:
        print(json.dumps(rows, indent=1))
    print(f"{len(rows) - failed}/{len(rows)} cases as expected")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
