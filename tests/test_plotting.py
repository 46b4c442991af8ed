"""Smoke tests: every plotting function returns a figure and writes a non-empty PNG from small synthetic
data; the figures are drawn without pyplot, into an ``ax=`` / ``fig=`` of the caller's when given."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jaxtraffic.paper import plotting

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
RHO_BAR, V_BAR, H_BAR = 0.10735931, 3.104839, 1.5


def assert_png(path, fig=None) -> None:
    """A real PNG at ``path``; ``fig``: the returned figure (a matplotlib Figure with axes)."""
    from matplotlib.figure import Figure

    if fig is not None:
        assert isinstance(fig, Figure) and fig.axes
    assert path.exists(), path
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert len(data) > 5000  # a real picture, not an empty canvas


@pytest.fixture
def series():
    t = np.linspace(0.0, 30.0, 31)
    decay = np.exp(-t / 10.0)
    grow = np.exp(t / 40.0)
    return t, decay, grow


def test_learning_curve(tmp_path):
    csv = tmp_path / "learning_curve.csv"
    lines = ["update,env_steps,wall_s,mean_reward,eval_reward,extra"]
    for u in range(12):
        ev = "" if u % 3 else f"{-50.0 * math.exp(-u / 2.0):.4f}"  # evaluation only every 3rd update
        lines.append(f"{u},{(u + 1) * 1000},{1.5 * u:.2f},{-80.0 * math.exp(-u / 3.0):.4f},{ev},x")
    csv.write_text("\n".join(lines) + "\n")
    out = plotting.plot_learning_curve(csv, tmp_path / "lc.png")
    assert_png(tmp_path / "lc.png", out)
    data = plotting.read_learning_curve(csv)
    assert np.isnan(data["eval_reward"][1]) and data["env_steps"][-1] == 12000


def test_learning_curve_rejects_empty(tmp_path):
    csv = tmp_path / "empty.csv"
    csv.write_text("update,env_steps,wall_s,mean_reward,eval_reward\n")
    with pytest.raises(ValueError):
        plotting.plot_learning_curve(csv, tmp_path / "lc.png")


def test_reward(tmp_path, series):
    t, decay, grow = series
    seeds = np.stack([-decay * (1 + 0.1 * k) for k in range(3)])
    out = plotting.plot_reward(tmp_path / "reward.png", t,
                        {"open loop (D = 4 s)": -grow, "PPO (D = 4 s)": seeds, "Lyapunov (D = 0)": -decay},
                        markers={"open loop (D = 4 s)": 20.0})
    assert_png(tmp_path / "reward.png", out)


def test_spacetime(tmp_path, series):
    t, decay, _ = series
    x = np.linspace(0.0, 1000.0, 21)
    wave = np.cos(8 * np.pi * (x[None, :] - 3.0 * t[:, None]) / 1000.0)
    rho = RHO_BAR + 0.01 * wave * decay[:, None]
    v = 0.3333 / rho
    rows = {"open loop": (rho, v, np.full_like(rho, H_BAR)),  # constant h panel gets a note
            "PPO": (RHO_BAR + 0.5 * (rho - RHO_BAR), v, H_BAR + 0.2 * wave)}
    out = plotting.plot_spacetime(tmp_path / "st.png", t, x, rows, (RHO_BAR, V_BAR, H_BAR), "synthetic",
                           diverged_at={"open loop": 25.0})
    assert_png(tmp_path / "st.png", out)


def test_fields_on_uniform_grids_are_images_placed_on_their_cells():
    """``_field_image``: recorded float32 times (spacing varying by ~1e-5 s) count as uniform and are
    drawn as one image whose pixels are centred on (t, x); a non-uniform grid falls back to a mesh."""
    from matplotlib.collections import QuadMesh
    from matplotlib.figure import Figure
    from matplotlib.image import AxesImage

    t = np.append(np.arange(300, dtype=np.float32) * np.float32(1.0000001), np.float32(300.0))
    x = np.linspace(0.0, 1000.0, 21)
    f = np.zeros((t.size, x.size))
    ax = Figure().subplots()
    img = plotting._field_image(ax, t, x, f)
    assert isinstance(img, AxesImage)
    np.testing.assert_allclose(img.get_extent(), (-0.5, 300.5, -25.0, 1025.0), rtol=1e-6)
    assert isinstance(plotting._field_image(ax, t, x ** 1.5, f), QuadMesh)


def test_l2_norms_and_panels(tmp_path, series):
    t, decay, grow = series
    s = {"backstepping": (0.007 * decay, 0.2 * decay),
         "PPO": (np.stack([0.007 * decay, 0.008 * decay]), np.stack([0.2 * decay, 0.3 * decay]))}
    assert_png(tmp_path / "l2.png", plotting.plot_l2_norms(tmp_path / "l2.png", t, s, "synthetic L2"))
    assert_png(tmp_path / "l2p.png", plotting.plot_l2_panels(tmp_path / "l2p.png", t, {"D = 3 s": s, "D = 5 s": {
        "open loop": (0.007 * grow, 0.2 * grow)}}, "synthetic panels"))


def test_robustness_map(tmp_path):
    delays = np.array([0.0, 2.0, 4.0, 6.0, 8.0])
    alphas = np.array([0.05, 0.15, 0.3, 0.6])
    base = 0.001 * (1 + delays[:, None]) * (1 + 10 * np.abs(alphas[None, :] - 0.15))
    div = base > 0.02
    maps = {"open loop": (base * 3, base * 3 > 0.02), "PPO": (base, div),
            "all diverged": (base, np.ones_like(div)),
            "none": (np.where(div, np.nan, base), np.zeros_like(div))}
    out = plotting.plot_robustness_map(tmp_path / "robust.png", delays, alphas, maps, "synthetic robustness",
                                initial_l2=0.007)
    assert_png(tmp_path / "robust.png", out)
    # a single controller, a single cell
    out = plotting.plot_robustness_map(tmp_path / "one.png", delays[:1], alphas[:1],
                                {"PPO": (base[:1, :1], div[:1, :1])}, "one cell", nominal=None)
    assert_png(tmp_path / "one.png", out)


def test_learning_curve_renamed_column(tmp_path):
    """``eval_rho_L2`` (veh/km) is now ``eval_rho_L2_veh_km``: older CSVs and resumed rows read as it."""
    from jaxtraffic.runs.curve import CURVE_FIELDS, read_learning_curve, write_curve

    old = tmp_path / "old.csv"
    old.write_text("update,eval_rho_L2\n1,0.5\n")
    assert read_learning_curve(old)["eval_rho_L2_veh_km"].tolist() == [0.5]
    new = tmp_path / "new.csv"
    write_curve(new, [{"update": 1, "eval_rho_L2": 0.5}])  # a row saved by an older run, then resumed
    data = read_learning_curve(new)
    assert list(data) == CURVE_FIELDS and data["eval_rho_L2_veh_km"][0] == 0.5


def test_draws_into_the_callers_axes_and_subfigures_without_a_file(series):
    """``ax=`` / ``fig=``: the figures compose into one of the caller's; no path, no file."""
    from matplotlib.figure import Figure

    t, decay, grow = series
    fig = Figure(figsize=(12, 8), layout="constrained")
    left, right = fig.subfigures(1, 2)
    ax = left.subplots()
    assert plotting.plot_reward(None, t, {"PPO (D = 4 s)": -decay}, ax=ax) is left  # the (sub)figure of ax
    assert ax.get_yscale() == "log" and ax.lines
    s = {"backstepping": (0.007 * decay, 0.2 * decay)}
    assert plotting.plot_l2_norms(None, t, s, "into a subfigure", fig=right) is right
    assert len(right.axes) == 2 and len(fig.axes) == 3


def test_importing_the_library_and_plotting_leave_matplotlib_alone():
    """No backend switch and no pyplot figures: ``import jaxtraffic`` and the plotting functions leave a
    notebook's matplotlib as it was (the backend is chosen by matplotlib, not by the library)."""
    import subprocess
    import sys

    code = """
import matplotlib
before = matplotlib.rcParams._get_backend_or_none()
import numpy as np
import jaxtraffic
from jaxtraffic.paper import plotting
plotting.plot_reward(None, np.arange(3.0), {"PPO": -np.ones(3)})
import sys
print(before, matplotlib.rcParams._get_backend_or_none(), "matplotlib.pyplot" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**__import__("os").environ, "MPLBACKEND": ""})
    assert out.returncode == 0, out.stderr[-2000:]
    before, after, pyplot = out.stdout.split()
    assert before == after == "None" and pyplot == "False"


def test_the_suffix_names_the_format_written(tmp_path, series):
    """A .pdf path receives a PDF (vector), .svg an SVG, .png a PNG; a suffix matplotlib cannot write (or none)
    is a clear error before anything is written."""
    t, decay, grow = series
    for name, head in (("r.pdf", b"%PDF-"), ("r.svg", b"<?xml"), ("r.png", PNG_MAGIC)):
        plotting.plot_reward(tmp_path / name, t, {"a": -decay, "b": -grow})
        assert (tmp_path / name).read_bytes().startswith(head), name
    assert b"<svg" in (tmp_path / "r.svg").read_bytes()[:1000]
    for bad, why in (("r.docx", "matplotlib cannot write .docx files"), ("r", "no suffix to name the format")):
        with pytest.raises(ValueError, match=why):
            plotting.plot_reward(tmp_path / "new" / bad, t, {"a": -decay})
    assert not (tmp_path / "new").exists()


def test_spacetime_png_is_screen_sized(tmp_path):
    """A space-time figure at the paper's grid (3 001 recordings x 201 cells) is written at screen resolution:
    one colour bar per column, ``COLOUR_LEVELS`` colours a map, at most 1 300 pixels wide and a few tens of kB a
    row (docs/results holds ten of them; with the smoothing filter and a continuous map: 125 kB a row)."""
    from PIL import Image

    t, x = np.linspace(0.0, 300.0, 3001), np.linspace(2.5, 997.5, 201)
    wave = np.sin(2 * np.pi * (x[None, :] + 3.0 * t[:, None]) / 166.0) * np.exp(-t / 60.0)[:, None]
    rows = {f"law {k}": (RHO_BAR + 0.01 * wave / (k + 1), V_BAR - 0.4 * wave / (k + 1), H_BAR + 0.3 * wave / (k + 1))
            for k in range(3)}
    fig = plotting.plot_spacetime(tmp_path / "st.png", t, x, rows, (RHO_BAR, V_BAR, H_BAR), "paper grid")
    images = [a for ax in fig.axes for a in ax.get_images()]
    assert len(images) == 9 and all(im.get_cmap().N == plotting.COLOUR_LEVELS for im in images)
    assert len(fig.axes) == 9 + 3  # the panels and one colour bar per column
    with Image.open(tmp_path / "st.png") as png:
        assert png.mode == "P" and png.size[0] <= 1300
    assert (tmp_path / "st.png").stat().st_size < 40_000 * len(rows)
