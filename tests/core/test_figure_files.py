"""A figure's PNG (a palette of at most 256 colours) against matplotlib's own RGBA
PNG of the same figure: the same size, the same pixels up to the quantizer's
rounding; a figure with transparency keeps its alpha exactly (docs/performance.md#figure-files)."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from svrobs_core.report.figure_files import figure_bytes, palette_png
from svrobs_core.report.plotting import new_figure
from svrobs_core.report.style import figure_style


def _figure():
    fig, axes = new_figure(1, 2, (6.0, 2.5))
    x = np.linspace(0.0, 10.0, 300)
    for ax in np.ravel(axes):
        for k in range(6):
            ax.plot(x, np.sin(x + k) * (1 + k), label=f"series {k}")
        ax.set_title("panel")
        ax.legend(fontsize=6)
    return fig


def _matplotlib_png(fig, **kwargs) -> Image.Image:
    buf = io.BytesIO()
    with figure_style():
        fig.savefig(buf, format="png", dpi=200, **kwargs)
    return Image.open(buf)


def test_the_png_is_matplotlibs_image_in_a_palette():
    fig = _figure()
    ours = Image.open(io.BytesIO(figure_bytes(fig, "png")))
    ref = _matplotlib_png(fig)
    assert ours.format == "PNG" and ours.mode == "P" and ours.size == ref.size
    assert len(ours.getcolors(256) or []) <= 256
    a = np.asarray(ours.convert("RGB"), dtype=int)
    b = np.asarray(ref.convert("RGB"), dtype=int)
    err = np.abs(a - b).max(axis=2)
    assert np.abs(a - b).mean() < 3.0  # of 255
    assert np.mean(err > 24) < 0.002  # the antialiasing's rarest shades move most
    # the background's white and the text's black stay exact
    for pure in (0, 255):
        where = (b == pure).all(axis=2)
        assert where.any() and (a[where] == pure).all()
    assert figure_bytes(fig, "png") == figure_bytes(fig, "png")  # deterministic


def test_a_transparent_figure_keeps_its_alpha_exactly():
    fig = _figure()
    fig.patch.set_alpha(0.0)
    ours = Image.open(io.BytesIO(figure_bytes(fig, "png")))
    buf = io.BytesIO()
    with figure_style():
        fig.savefig(buf, format="rgba", dpi=200)
    assert ours.mode == "RGBA"
    w, h = ours.size
    assert np.array_equal(
        np.asarray(ours), np.frombuffer(buf.getvalue(), np.uint8).reshape(h, w, 4)
    )


def _log_figure():
    """Tick labels that matplotlib draws as mathtext (the title is written as it is),
    on a transparent background (so the PNG keeps matplotlib's pixels exactly)."""
    fig, axes = new_figure(1, 1, (4.0, 2.5))
    ax = np.ravel(axes)[0]
    x = np.logspace(-3, 1, 50)
    ax.loglog(x, x**2)
    ax.set_title(r"$\|\hat A - A\|_2$ against $N$")
    fig.patch.set_alpha(0.0)
    return fig


def test_mathtext_is_parsed_once_per_thread_and_drawn_as_matplotlib_draws_it():
    from matplotlib.mathtext import MathTextParser

    figure_bytes(_log_figure(), "png")  # its labels parsed once
    misses = MathTextParser._parse_cached.cache_info().misses
    fig = _log_figure()  # a new figure: a new renderer
    ours = Image.open(io.BytesIO(figure_bytes(fig, "png")))
    assert MathTextParser._parse_cached.cache_info().misses == misses
    buf = io.BytesIO()
    with figure_style():
        fig.savefig(buf, format="rgba", dpi=200)
    w, h = ours.size
    assert ours.mode == "RGBA"
    assert np.array_equal(
        np.asarray(ours), np.frombuffer(buf.getvalue(), np.uint8).reshape(h, w, 4)
    )


def test_a_users_name_is_drawn_as_written_and_the_tick_labels_as_mathtext():
    """A system or job name that is not mathtext (``$\\frac{a$``) in a title, a legend
    or a note fails no draw (it failed the report); the tick labels are still mathtext."""
    fig = _log_figure()
    ax = fig.axes[0]
    name = r"$\frac{a$ \x"
    ax.plot([1e-3, 10.0], [1.0, 2.0], label=name)
    ax.legend(title=name)
    ax.text(0.5, 0.5, name)
    fig.suptitle(name)
    for fmt, magic in (("png", b"\x89PNG"), ("svg", b"<?xml")):
        assert figure_bytes(fig, fmt).startswith(magic)
    ticks = [t for t in ax.get_yticklabels() if t.get_text()]
    assert ticks and all(t.get_text().startswith("$") and t.get_parse_math() for t in ticks)


def test_each_thread_draws_with_its_own_mathtext_parser():
    """A parse holds the fonts of the thread that made it (matplotlib keeps FreeType
    fonts per thread): another thread gets its own parser, this one keeps its own."""
    import threading

    from svrobs_core.report import figure_files

    here = figure_files._mathtext_parser()
    there = []
    t = threading.Thread(target=lambda: there.append(figure_files._mathtext_parser()))
    t.start()
    t.join()
    assert there and there[0] is not here and figure_files._mathtext_parser() is here


def test_a_forked_child_draws_with_parsers_of_its_own():
    """The parent's parser (its cached parses hold fonts whose file offset a forked
    child would share) is not the child's; the child's parser draws the same pixels."""
    import os

    from svrobs_core.report import figure_files

    fig = _log_figure()  # mathtext tick labels
    want = figure_files.figure_bytes(fig, "png")
    here = figure_files._mathtext_parser()
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: report by its exit code, never return into pytest
        code = 1
        try:
            fresh = getattr(figure_files._parsers, "parser", None) is None
            mine = figure_files._mathtext_parser() is not here
            same = figure_files.figure_bytes(fig, "png") == want
            code = 0 if fresh and mine and same else 2
        finally:
            os.write(write, bytes([code]))
            os._exit(0)
    os.close(write)
    got = os.read(read, 1)
    os.waitpid(pid, 0)
    os.close(read)
    assert got == bytes([0])
    assert figure_files._mathtext_parser() is here


def test_an_unpickled_figure_at_an_inexact_width_gives_the_same_png():
    """12.7 cm at 200 dpi is 999.99... pixels in floating point: the size comes from
    the renderer, also for a Figure that lost its Agg canvas in a pickle."""
    import pickle

    fig = _figure()
    fig.set_size_inches(12.7 / 2.54, 2.0)
    ours = Image.open(io.BytesIO(figure_bytes(pickle.loads(pickle.dumps(fig)), "png")))
    assert ours.size == _matplotlib_png(fig).size == (1000, 400)
    assert ours.info["dpi"] == pytest.approx((200, 200), abs=0.01)


def test_raw_bytes_that_are_not_the_size_are_refused():
    with pytest.raises(ValueError, match="not 3 x 2 pixels"):
        palette_png(bytes(4 * 3 * 2 + 4), (3, 2), 200)
    with pytest.raises(ValueError, match="fmt must be one of png, svg, pdf"):
        figure_bytes(_figure(), "gif")


def test_one_draw_gives_savefigs_pixels_and_the_files_skip_the_layout_pass():
    """The PNG's one draw (layout engine inside it) gives the pixels savefig's
    two draws give; after it the figure has no layout engine, so SVG and PDF are
    drawn once, with the layout the PNG fixed."""
    from svrobs_core.report.build import ReportFigure

    fig = _figure()
    buf = io.BytesIO()
    with figure_style():
        fig.savefig(buf, format="rgba", dpi=200)  # the oracle: matplotlib's own path
    w, h = (int(round(v * 200)) for v in fig.get_size_inches())
    want = palette_png(buf.getvalue(), (w, h), 200)
    rf = ReportFigure("f", "t", "c", "E1", _figure())
    assert rf.png() == want
    assert rf.figure.get_layout_engine() is None
    positions = [ax.get_position().bounds for ax in rf.figure.axes]
    assert rf.svg().startswith(b"<?xml") and rf.pdf().startswith(b"%PDF")
    assert [ax.get_position().bounds for ax in rf.figure.axes] == positions
