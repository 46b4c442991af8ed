"""Figures drawn without pyplot, written atomically: the lowest layer's plotting helpers.

Figures are ``matplotlib.figure.Figure`` objects, never made through pyplot: no backend is chosen and
nothing global changes, so plotting works the same in a script, under the command lines and in a
notebook (where a returned figure displays itself). Imports nothing of jaxtraffic but ``files``.
"""

from __future__ import annotations

import io
from pathlib import Path

from matplotlib.figure import Figure, SubFigure

from jaxtraffic.io.files import atomic_write_bytes

__all__ = ["DPI", "figure_format", "finish_figure", "new_figure", "save_figure"]

DPI = 100  # dots per inch of every PNG: screen resolution (a 13 in wide figure is 1 300 pixels)
PNG_COLOURS = 256  # a PNG is written with a palette of this many colours: a third of the bytes of full colour


def _palette_png(data: bytes) -> bytes:
    """``data`` (a full-colour PNG) as a PNG with a palette of ``PNG_COLOURS`` (median cut, no dithering):
    screen resolution, about a third of the size for the space-time fields."""
    from PIL import Image  # matplotlib's own dependency

    out = io.BytesIO()
    image = Image.open(io.BytesIO(data)).convert("RGB")
    image.quantize(colors=PNG_COLOURS, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
        out, format="PNG", optimize=True)
    return out.getvalue()


def new_figure(fig: Figure | SubFigure | None = None, **kwargs) -> Figure | SubFigure:
    """``fig`` (a figure or subfigure of the caller's to draw into), else a new ``Figure`` with constrained
    layout (``kwargs``: e.g. ``figsize``), made without pyplot."""
    return Figure(layout="constrained", **kwargs) if fig is None else fig


def figure_format(path: str | Path) -> str:
    """The file format ``path``'s suffix names (``.png``, ``.pdf``, ``.svg``, ... : what matplotlib writes);
    ``ValueError`` for a suffix it cannot write, or none."""
    suffix = Path(path).suffix.lower().removeprefix(".")
    known = Figure().canvas.get_supported_filetypes()
    if suffix not in known:
        raise ValueError(f"figure path {path}: " + (f"matplotlib cannot write .{suffix} files" if suffix else
                         "no suffix to name the format") + f"; use one of {', '.join('.' + k for k in known)}")
    return suffix


def save_figure(fig: Figure | SubFigure, png_path: str | Path) -> Path:
    """Write ``fig`` (the whole figure a subfigure belongs to) at ``png_path``, atomically, in the format its
    suffix names (``figure_format``: PNG at ``DPI`` with a palette of ``PNG_COLOURS`` for ``.png``, a vector PDF
    for ``.pdf``, ...)."""
    png_path = Path(png_path)
    fmt = figure_format(png_path)  # (checked before anything is written)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()  # written atomically: replaces a symbolic link at png_path instead of following it
    root = fig.figure if isinstance(fig, SubFigure) else fig
    root.savefig(buf, format=fmt, dpi=DPI, bbox_inches="tight")
    atomic_write_bytes(png_path, _palette_png(buf.getvalue()) if fmt == "png" else buf.getvalue())
    return png_path


def finish_figure(fig: Figure | SubFigure, png_path: str | Path | None) -> Figure | SubFigure:
    """Save ``fig`` at ``png_path`` when one is given (in the format its suffix names); return it."""
    if png_path is not None:
        save_figure(fig, png_path)
    return fig
