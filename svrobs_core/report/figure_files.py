"""A figure's files: PNG, SVG and PDF bytes in memory, with deterministic metadata
(docs/performance.md#figure-files).

The PNG is the Agg rendering reduced to a palette of at most 256 colours (Pillow's
fast octree quantizer): a plot has few colours beyond its antialiasing, so the file
is about a third of the RGBA one matplotlib writes and takes less time to encode
(one byte per pixel to compress instead of four). A palette colour within 2
levels of white or black is set to it, so the background and the text stay exact
unless a large near-white area shares their bucket. SVG keeps text as text; PDF
embeds its TrueType fonts."""

from __future__ import annotations

import io
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np

from .style import figure_style

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.figure import Figure
    from matplotlib.mathtext import MathTextParser, VectorParse

FORMATS = ("png", "svg", "pdf")
PNG_COLOURS = 256
SNAP = 2  # levels of 255


def figure_bytes(fig: Figure, fmt: str = "png", dpi: int = 200) -> bytes:
    """Render a Figure to PNG, SVG or PDF bytes."""
    if fmt not in FORMATS:
        raise ValueError(f"fmt must be one of {', '.join(FORMATS)}, got {fmt!r}")
    buf = io.BytesIO()
    meta = {"svg": {"Date": None}, "pdf": {"CreationDate": None}}
    _plain_text(fig)
    with figure_style():
        if fmt == "png":
            from matplotlib.backends.backend_agg import FigureCanvasAgg

            # an unpickled Figure has a base canvas: draw on an Agg one, whose
            # renderer then holds the pixels' size (whatever savefig's rc crops)
            canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
            # one draw at the file's dpi (savefig draws twice for a layout engine:
            # a dry pass, then the pixels); the layout engine runs in the draw
            with _figure_dpi(fig, dpi):
                # the renderer the draw reuses, with this thread's one mathtext parser
                renderer = canvas.get_renderer()  # type: ignore[no-untyped-call]
                renderer.mathtext_parser = _mathtext_parser()
                canvas.draw()  # type: ignore[no-untyped-call]
                rgba = bytes(canvas.buffer_rgba())  # type: ignore[no-untyped-call]
                size = (int(canvas.renderer.width), int(canvas.renderer.height))
            return palette_png(rgba, size, dpi)
        fig.savefig(buf, format=fmt, dpi=dpi, metadata=meta[fmt])
    return buf.getvalue()


def _plain_text(fig: Figure) -> None:
    """Every text of ``fig`` but its tick labels is drawn as written, never parsed as
    mathtext: a title, legend or note may hold a user's name (a system, a job), and a
    name such as ``$\\frac{a$`` would fail the draw, and with it the report. The
    report's own text has no mathtext; its tick labels (``$10^{-2}$``) and axis offsets,
    which an Axis holds, keep it."""
    from matplotlib.axis import Axis
    from matplotlib.text import Text

    stack: list[Artist] = [fig]
    while stack:
        artist = stack.pop()
        for child in artist.get_children():
            if isinstance(child, Axis):  # its ticks are made at the draw: not walked
                child.label.set_parse_math(False)
                continue
            if isinstance(child, Text):
                child.set_parse_math(False)
            stack.append(child)


_parsers = threading.local()


def _forget_parsers() -> None:
    """In a forked child: parsers of its own. A parse the parent cached holds the
    parent's FreeType fonts, whose font files the child shares with it (one file
    offset for both processes), so two processes drawing its glyphs at once read
    each other's bytes ("FT_Load_Glyph ... invalid outline"). matplotlib forgets its
    own fonts at a fork in the same way."""
    global _parsers
    _parsers = threading.local()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_parsers)


def _mathtext_parser() -> MathTextParser[VectorParse]:
    """The mathtext parser of every PNG drawn in this thread. Its parse cache is keyed
    by the parser, so a renderer's own parser (one per figure) parses each tick label
    again; with one parser they are parsed once per thread (the same pixels,
    docs/performance.md#figure-files). One per thread, not per process: a parse holds
    the FreeType fonts of the thread that made it (matplotlib keeps fonts per thread),
    and a font drawn from two threads at once fails ("FT_Load_Glyph ... invalid
    outline", seen while `svrobs reproduce` drew figures in its background thread)."""
    parser = getattr(_parsers, "parser", None)
    if parser is None:
        from matplotlib.mathtext import MathTextParser

        parser = _parsers.parser = MathTextParser("path")  # as RendererAgg makes its own
    return parser


@contextmanager
def _figure_dpi(fig: Figure, dpi: int) -> Iterator[None]:
    """The figure at ``dpi`` for a while (as ``savefig(dpi=...)`` sets it)."""
    old = fig.dpi
    fig.dpi = dpi
    try:
        yield
    finally:
        fig.dpi = old


def palette_png(rgba: bytes, size: tuple[int, int], dpi: int) -> bytes:
    """PNG bytes (``dpi`` recorded) of a raw RGBA image of ``size`` = (width, height)
    pixels: RGB reduced to a palette of ``PNG_COLOURS`` colours when every pixel is
    opaque, else RGBA as it is."""
    from PIL import Image

    width, height = size
    pixels = np.frombuffer(rgba, dtype=np.uint8)
    if width <= 0 or height <= 0 or pixels.size != 4 * width * height:
        raise ValueError(f"{pixels.size} RGBA bytes are not {width} x {height} pixels")
    image = Image.frombuffer("RGBA", (width, height), rgba, "raw", "RGBA", 0, 1)
    if pixels[3::4].min(initial=255) == 255:
        image = image.convert("RGB").quantize(PNG_COLOURS, method=Image.Quantize.FASTOCTREE)
        # the octree's colours are its buckets' means: a channel within SNAP of its end
        # is put at the end, so a bucket of white (the background) or black (the
        # text) is exactly that
        palette = np.array(image.getpalette() or [], dtype=np.int16)
        palette[palette >= 255 - SNAP] = 255
        palette[palette <= SNAP] = 0
        image.putpalette(palette.astype(np.uint8).tobytes())
    out = io.BytesIO()
    image.save(out, format="png", dpi=(dpi, dpi))
    return out.getvalue()
